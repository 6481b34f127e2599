#!/bin/sh
# check_internal_headers.sh SOURCE_DIR: a core subsystem's internal header (core/<sub>/*_internal.hpp)
# is included only by the files of core/<sub>/ (docs/architecture.md, "Public and internal").
set -eu
cd "$1"
status=0
for header in core/*/*_internal.hpp; do
  sub=$(dirname "$header")
  name="$(basename "$sub")/$(basename "$header")"
  for file in $(grep -rl --include='*.cpp' --include='*.hpp' --include='*.h' --include='*.c' \
                  "#include \"$name\"" core plugin aravis_source v4l2_source tests 2>/dev/null); do
    case "$file" in
      "$sub"/*) ;;
      *) echo "$file includes $name, internal to $sub/"; status=1 ;;
    esac
  done
done
exit $status
