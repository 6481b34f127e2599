#!/bin/sh
# abi_dump.sh HEADER LIBRARY: the C ABI as text: posecal.h without comments and blank lines, then
# the library's exported symbols with their versions.
set -eu
header="$1"; lib="$2"
echo "# posecal.h declarations (comments stripped)"
gcc -w -fpreprocessed -dD -E -P -x c "$header" | sed -e 's/[[:space:]]\+/ /g' -e 's/^ //' -e 's/ $//' | grep -v '^$'
echo "# exported symbols"
nm -D --defined-only --with-symbol-versions "$lib" | awk '{print $2, $3}' | sort
