# The system libraries forestmap needs and how to find them; sourced by scripts/setup.sh (and by
# tests/io/test_setup_script.py). Safe under `set -euo pipefail`: no pipeline whose reader stops
# early (`ldconfig -p | grep -q` loses the race with SIGPIPE when the cache is long, and under
# pipefail reports a present library as missing).

# library file name => apt packages that provide it (and what needs it)
SYSTEM_LIBS=(
  'libusb-1.0.so.0|libusb-1.0-0|open3d'
  'libEGL.so.1|libegl1 libgl1-mesa-dri|pyvista/VTK off-screen rendering'
)

# The dynamic linker's cache, read once (empty when ldconfig is not there; /sbin is often not on
# a normal user's PATH).
_ldconfig_cache() {
  if [ -z "${_LDCACHE_READ:-}" ]; then
    _LDCACHE=""
    local ldconfig
    for ldconfig in "$(command -v ldconfig || true)" /sbin/ldconfig /usr/sbin/ldconfig; do
      if [ -n "$ldconfig" ] && [ -x "$ldconfig" ]; then
        _LDCACHE="$("$ldconfig" -p 2>/dev/null || true)"
        break
      fi
    done
    _LDCACHE_READ=1
  fi
}

# where_lib NAME: prints where the library NAME (e.g. libEGL.so.1) is found ("ldconfig" or its
# path) and returns 0, or returns 1. Looks in ldconfig's cache, then in $LD_LIBRARY_PATH and the
# usual library folders.
where_lib() {
  local name="$1" dir
  _ldconfig_cache
  # ldconfig -p lines: "<TAB>libEGL.so.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libEGL.so.1"
  if [ -n "$_LDCACHE" ] && grep -qF -- "$(printf '\t%s (' "$name")" <<<"$_LDCACHE"; then
    echo "ldconfig"
    return 0
  fi
  local dirs=()
  if [ -n "${LD_LIBRARY_PATH:-}" ]; then IFS=: read -r -a dirs <<<"$LD_LIBRARY_PATH"; fi
  for dir in "${dirs[@]}" /lib/*-linux-gnu /usr/lib/*-linux-gnu /lib64 /usr/lib64 /lib /usr/lib \
             /usr/local/lib; do
    if [ -n "$dir" ] && [ -e "$dir/$name" ]; then
      echo "$dir/$name"
      return 0
    fi
  done
  return 1
}

have_lib() { where_lib "$1" >/dev/null; }

# check_system_libs: one line per system library, "<name> found (<where>)" or
# "<name> missing (apt: <packages>; for <what>)"; sets MISSING_PACKAGES to the apt packages of
# the missing ones. Always returns 0.
check_system_libs() {
  local entry name packages what where
  MISSING_PACKAGES=()
  _ldconfig_cache  # once, here: where_lib runs in a subshell below
  for entry in "${SYSTEM_LIBS[@]}"; do
    IFS='|' read -r name packages what <<<"$entry"
    if where="$(where_lib "$name")"; then
      echo "$name found ($where)"
    else
      echo "$name missing (apt: $packages; for $what)"
      # shellcheck disable=SC2206  # the package list splits on spaces
      MISSING_PACKAGES+=($packages)
    fi
  done
}
