#!/usr/bin/env bash
# Headless browser for tests/test_web.py: Debian's `chromium` package, driven by
# Playwright for Python as its executable. Idempotent; only Debian packages are
# downloaded (never `playwright install`). Needs root (or sudo) when it installs.
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
    echo "install-browser: $(command -v chromium) is already installed"
    exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo"
fi
$SUDO apt-get update
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium
command -v chromium >/dev/null 2>&1 || { echo "install-browser: chromium is still not on PATH" >&2; exit 1; }
echo "install-browser: installed $(command -v chromium)"
