#!/usr/bin/env bash
# System packages the PDF report and its checks need:
#   libharfbuzz-subset0  WeasyPrint font subsetting
#   poppler-utils        pdftoppm (PDF -> PNG pages in tests)
#   chromium             headless screenshot of the HTML report in tests
# Installs only what is missing; needs root (or sudo). Without either it says what to install.
set -euo pipefail
wanted=(libharfbuzz-subset0 poppler-utils chromium)
missing=()
for p in "${wanted[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
  echo "flowcast: missing system packages: ${missing[*]} (need root to install: apt-get install ${missing[*]})" >&2
  exit 0
fi
echo "flowcast: installing system packages: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
