# The posecal Python package's version: pyproject.toml reads it from here (so keep this file
# a single assignment), posecal.__version__ re-exports it. It follows the library's version,
# CMakeLists.txt's project(posecal VERSION ...): test_binding_package.py checks that they are
# equal.
__version__ = "0.1.0"
