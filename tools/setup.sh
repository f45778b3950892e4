#!/usr/bin/env bash
# Installs everything usdfiber needs on a fresh Debian machine with Python >= 3.10:
# Debian's libllvm19 (Mitsuba's LLVM variants abort with older LLVMs) and the package
# itself, editable, with its test dependencies. Safe to run again: it skips what is done.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

llvm_present() { ls /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1 || ls /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1; }
if ! llvm_present; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "usdfiber setup: installing libllvm19 (apt-get)"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "usdfiber setup: libllvm19 not found and no apt-get; install LLVM >= 16 and set DRJIT_LIBLLVM_PATH" >&2
  fi
fi

# Reinstall only when the build inputs changed (the stamp holds their hash).
stamp=build/.setup-stamp
want=$(cat pyproject.toml CMakeLists.txt schema/schema.usda schema/generated/* | sha256sum | cut -c1-16)
# (and when the installed usdfiber is another checkout's: an editable install names one tree)
here_imported() {
  "$PY" -c "import pathlib, sys, usdfiber; sys.exit(pathlib.Path(usdfiber.__file__).resolve().parents[1] != pathlib.Path.cwd().resolve())" >/dev/null 2>&1
}
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! here_imported; then
  echo "usdfiber setup: pip install -e .[test]"
  "$PY" -m pip install -q --disable-pip-version-check --root-user-action=ignore -e ".[test]"
  mkdir -p build && echo "$want" > "$stamp"
  # pyenv exposes new console scripts (usdfiber) only after a rehash.
  if command -v pyenv >/dev/null 2>&1; then pyenv rehash || true; fi
fi
