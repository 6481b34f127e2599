"""Prints where, relative to an install prefix, this Python looks for pure-Python packages:
the lib/python3.N/dist-packages (Debian) or lib/python3.N/site-packages part of its first site
directory, e.g. lib/python3.11/dist-packages for Debian 12's /usr/local/lib/python3.11/
dist-packages. plugin/CMakeLists.txt installs the posecal package there; for the prefixes /usr
and /usr/local Debian's python3 then finds it without PYTHONPATH."""
import re
import site
import sys

for d in site.getsitepackages():
    m = re.search(r"lib/python3\.[0-9]+/(dist|site)-packages$", d)
    if m:
        print(m.group(0))
        sys.exit(0)
sys.exit("no lib/python3.N/{dist,site}-packages among %s" % site.getsitepackages())
