# Helpers shared by loglio's scripts. Source it; do not run it.

# Each section header carries the UTC time, so a CI log shows what each part costs (CI must stay
# under 30 minutes; on a 2.5 GHz Xeon it took 27).
section() { printf '\n==== %s ==== (%s)\n' "$*" "$(date -u +%H:%M:%S)"; }

# Loud, unmissable notice that one part is skipped because a tool cannot be installed here.
skip_loudly() {
  printf '\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n' >&2
  printf '!!! SKIPPED: %s\n' "$*" >&2
  printf '!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\n' >&2
}

# ensure_rust_target TRIPLE: installs a rustup target; returns 1 (after a loud notice) if impossible.
ensure_rust_target() {
  if rustup target list --installed 2>/dev/null | grep -qx "$1"; then return 0; fi
  if rustup target add "$1" >/dev/null 2>&1; then return 0; fi
  skip_loudly "rustup target $1 could not be installed; everything that needs it is skipped"
  return 1
}

# ensure_apt PKG...: installs Debian packages if missing; returns 1 (after a loud notice) if impossible.
ensure_apt() {
  local missing=()
  for p in "$@"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  [ ${#missing[@]} -eq 0 ] && return 0
  local sudo=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && sudo="sudo"
  if { $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"; } >/dev/null 2>&1; then
    return 0
  fi
  skip_loudly "apt packages ${missing[*]} could not be installed; everything that needs them is skipped"
  return 1
}
