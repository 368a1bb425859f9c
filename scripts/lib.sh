# Helpers shared by loglio's scripts. Source it; do not run it.

# Each section header carries the UTC time, so a CI log shows what each part costs (CI must stay
# under 45 minutes; a clean clone took 19.5 on the 2-core AMD EPYC on 2026-11-27).
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

# The independent peers of the live-output tests (pymavlink, Cyclone DDS, a WebSocket client,
# the mcap reader) in a venv under target/ from PyPI. Exports LOGLIO_PYTHON (the venv's python)
# and LOGLIO_REQUIRE_PEERS=1, which turns the tests' SKIPPED into a failure; returns 1 after a
# loud notice when the venv cannot be made.
ensure_py_peers() {
  local venv="target/pyenv"
  local pkgs=(pymavlink==2.4.50 cyclonedds==11.0.1 websockets==15.0.1 mcap==1.6.0)
  local stamp="$venv/.loglio-peers"
  if [ ! -x "$venv/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "${pkgs[*]}" ]; then
    if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q --disable-pip-version-check "${pkgs[@]}"; } >/dev/null 2>&1; then
      skip_loudly "the Python peers (${pkgs[*]}) could not be installed into $venv; the live-output tests against them are skipped"
      return 1
    fi
    echo "${pkgs[*]}" >"$stamp"
  fi
  LOGLIO_PYTHON="$(cd "$venv/bin" && pwd)/python"
  export LOGLIO_PYTHON
  export LOGLIO_REQUIRE_PEERS=1
}
