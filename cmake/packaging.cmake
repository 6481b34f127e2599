# Debian packages with CPack (docs/packaging.md): `cpack --config build/CPackConfig.cmake -G DEB`
# after a build. One package per install component (plugin/CMakeLists.txt):
#   lib    -> libposecal1       the shared library (SONAME libposecal.so.1)
#   dev    -> libposecal-dev    header, libposecal.so link, CMake package, pkg-config file
#   cli    -> posecal           the command line, the docs and examples
#   python -> python3-posecal   the Python package
# Each package carries the licence as /usr/share/doc/<package>/copyright. The runtime
# dependencies of the library and the CLI are computed by dpkg-shlibdeps from the Debian
# packages the binaries link; the packages depend on each other at exactly this version.

set(POSECAL_DEB_PACKAGES lib libposecal1 dev libposecal-dev cli posecal python python3-posecal)
set(_posecal_components lib dev cli python)

set(_posecal_pairs ${POSECAL_DEB_PACKAGES})
while(_posecal_pairs)
  list(POP_FRONT _posecal_pairs _component _package)
  string(TOUPPER ${_component} _upper)
  set(CPACK_DEBIAN_${_upper}_PACKAGE_NAME ${_package})
  install(FILES ${PROJECT_SOURCE_DIR}/LICENSE DESTINATION ${CMAKE_INSTALL_DATAROOTDIR}/doc/${_package}
    RENAME copyright COMPONENT ${_component})
endwhile()

# The user documentation and the examples go with the command line.
install(DIRECTORY ${PROJECT_SOURCE_DIR}/docs/ DESTINATION ${CMAKE_INSTALL_DATAROOTDIR}/doc/posecal
  COMPONENT cli FILES_MATCHING PATTERN "*.md" PATTERN "*.png" PATTERN "*.c" PATTERN "*.py")
install(FILES ${PROJECT_SOURCE_DIR}/README.md DESTINATION ${CMAKE_INSTALL_DATAROOTDIR}/doc/posecal
  COMPONENT cli)

set(CPACK_PACKAGE_NAME posecal)
set(CPACK_PACKAGE_VENDOR "the posecal authors")
set(CPACK_PACKAGE_CONTACT "posecal maintainers <posecal@localhost>")
set(CPACK_PACKAGE_VERSION ${PROJECT_VERSION})
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "camera calibration with efficient pose selection")
set(CPACK_RESOURCE_FILE_LICENSE ${PROJECT_SOURCE_DIR}/LICENSE)
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_COMPONENTS_ALL ${_posecal_components})
set(CPACK_DEB_COMPONENT_INSTALL ON)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)  # name_version-release_arch.deb
set(CPACK_DEBIAN_PACKAGE_RELEASE 1)
set(CPACK_DEBIAN_PACKAGE_HOMEPAGE "https://localhost/posecal")
set(_posecal_exact "${PROJECT_VERSION}-${CPACK_DEBIAN_PACKAGE_RELEASE}")

set(CPACK_DEBIAN_LIB_PACKAGE_SECTION libs)
set(CPACK_DEBIAN_LIB_PACKAGE_SHLIBDEPS ON)
# A shlibs file (libposecal1 only: the other packages hold no shared library) for packages that
# link libposecal.so.1.
set(CPACK_DEBIAN_PACKAGE_GENERATE_SHLIBS ON)
set(CPACK_DEBIAN_PACKAGE_GENERATE_SHLIBS_POLICY ">=")
string(CONCAT CPACK_COMPONENT_LIB_DESCRIPTION
  "camera calibration with efficient pose selection - shared library\n"
  "libposecal computes the next board pose that most improves a camera calibration,\n"
  "waits until the board is there, captures keyframes and stops when the calibration\n"
  "is good enough. It speaks GigE Vision / USB3 Vision (Aravis) and V4L2 and has a\n"
  "stable C ABI for inspection software.")

set(CPACK_DEBIAN_DEV_PACKAGE_SECTION libdevel)
set(CPACK_DEBIAN_DEV_PACKAGE_DEPENDS "libposecal1 (= ${_posecal_exact})")
string(CONCAT CPACK_COMPONENT_DEV_DESCRIPTION
  "camera calibration with efficient pose selection - development files\n"
  "The C header posecal.h, the libposecal.so link, the CMake package (find_package(posecal))\n"
  "and the pkg-config file.")

set(CPACK_DEBIAN_CLI_PACKAGE_SECTION graphics)
set(CPACK_DEBIAN_CLI_PACKAGE_SHLIBDEPS ON)
set(CPACK_DEBIAN_CLI_PACKAGE_DEPENDS "libposecal1 (= ${_posecal_exact})")
string(CONCAT CPACK_COMPONENT_CLI_DESCRIPTION
  "camera calibration with efficient pose selection - command line\n"
  "The posecal command: simulate, calibrate (live cameras, image folders), station (many\n"
  "cameras), evaluate, board; with the user documentation and examples.")

set(CPACK_DEBIAN_PYTHON_PACKAGE_SECTION python)
# The package is installed where the build's Python looks (plugin/cmake/python_site_dir.py:
# lib/python3.11/dist-packages with Debian 12's python3), so it needs that Python version; it
# loads libposecal1's library by a path relative to itself.
set(_posecal_python_depends "python3")
if(POSECAL_PYTHON_INSTALL_DIR MATCHES "python3\\.([0-9]+)/")
  math(EXPR _posecal_next_minor "${CMAKE_MATCH_1} + 1")
  set(_posecal_python_depends "python3 (>= 3.${CMAKE_MATCH_1}), python3 (<< 3.${_posecal_next_minor})")
endif()
set(CPACK_DEBIAN_PYTHON_PACKAGE_DEPENDS
  "libposecal1 (= ${_posecal_exact}), ${_posecal_python_depends}, python3-numpy")
string(CONCAT CPACK_COMPONENT_PYTHON_DESCRIPTION
  "camera calibration with efficient pose selection - Python 3\n"
  "The posecal Python package: sessions fed with numpy arrays, results as arrays.")

# dpkg-shlibdeps: the CLI links libposecal.so.1, which is in this build (its dependency is the
# exact version above).
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS_PRIVATE_DIRS ${CMAKE_LIBRARY_OUTPUT_DIRECTORY})

include(CPack)
