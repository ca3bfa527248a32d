#!/usr/bin/env bash
# Installs what the browser test needs when it is missing: Debian's chromium
# and chromium-driver, and Selenium from PyPI. Fails (never skips) when they
# cannot be installed.
set -euo pipefail
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    sudo_="" && [[ $(id -u) -ne 0 ]] && sudo_="sudo"
    $sudo_ apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_ apt-get install -y -qq chromium chromium-driver >/dev/null
fi
python3 -c 'import selenium' 2>/dev/null ||
    python3 -m pip install --quiet --disable-pip-version-check 'selenium>=4.20'
