#!/usr/bin/env bash
# Installs Debian's libllvm19 so Mitsuba's fast `llvm_ad_rgb` variant can run.
# Only as root and only where apt-get exists; otherwise prints a one-line notice and the
# simulator falls back to the `scalar_rgb` variant. Never fails the build.
set -u
if ls /usr/lib/*/libLLVM-19.so* /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" != "0" ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "notice: libllvm19 not installed (needs root and apt-get); Mitsuba will use the slower scalar_rgb variant"
  exit 0
fi
(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1 \
  || echo "notice: could not install libllvm19; Mitsuba will use the slower scalar_rgb variant"
exit 0
