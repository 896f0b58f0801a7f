#!/usr/bin/env bash
# Prints the Debian packages that own the shared libraries BINARIES link (ldd, dpkg -S),
# one per line: what a runtime image must install for them. A library no package
# owns fails (it would be missing at run time). Usage: runtime-packages.sh BINARY...
set -euo pipefail
linked=$(ldd "$@") || { echo "runtime-packages: ldd failed on $*" >&2; exit 1; }
for lib in $(awk '/=> not found/ { print "missing:" $1 } /=> \// { print $3 }' <<<"$linked" | sort -u); do
  case "$lib" in missing:*) echo "runtime-packages: ${lib#missing:} not found by the loader" >&2; exit 1 ;; esac
  # Debian 12 merges /lib into /usr/lib, and alternatives (libblas.so.3) are symlinks:
  # the path as the loader gives it, under /usr, or the file it points to.
  owner=$(dpkg -S "$lib" 2>/dev/null || dpkg -S "/usr$lib" 2>/dev/null || dpkg -S "$(realpath "$lib")" 2>/dev/null) \
    || { echo "runtime-packages: no Debian package owns $lib" >&2; exit 1; }
  echo "${owner%%:*}"
done | sort -u
