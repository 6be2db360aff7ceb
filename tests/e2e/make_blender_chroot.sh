#!/usr/bin/env bash
# make_blender_chroot.sh DIR
#
# Create (or reuse) a minimal Debian chroot in DIR that holds Debian's real `blender` binary
# (sid: 5.2.2 on Python 3.14; trixie: 4.3.2 on Python 3.13), python3-numpy, Mesa's software
# OpenGL/EGL (llvmpipe), and pytest with hypothesis for the core's tests on Debian's Python, for
# tests/e2e/. Idempotent: if DIR/usr/bin/blender already starts, nothing is done.
#
#   debootstrap --variant=minbase SUITE DIR
#   chroot DIR apt-get install --no-install-recommends blender python3-numpy \
#       libgl1-mesa-dri libegl-mesa0 libegl1 python3-pytest python3-hypothesis
#
# Needs root and a Debian-like host with apt-get (debootstrap is installed with apt-get if it is
# missing). No mounts are needed afterwards: `chroot DIR blender -b ...` runs with an empty /proc
# and /sys (Blender only warns "could not get a list of mounted file-systems"), so nothing has to
# be unmounted. debootstrap mounts /proc and /sys itself while it runs and unmounts them on exit.
#
# Environment: VPFFD_DEBIAN_MIRROR (default http://deb.debian.org/debian),
#              VPFFD_DEBIAN_SUITE  (default sid; trixie is the stable fallback).
# Exit codes: 0 ok; 1 failure; 2 usage; 3 not root; 4 debootstrap missing and not installable.
# Progress goes to stderr. About 70 s, ~300 MB downloaded, ~1.2 GB on disk.
set -euo pipefail

SUITE="${VPFFD_DEBIAN_SUITE:-sid}"
MIRROR="${VPFFD_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
# Blender; Mesa's OpenGL (libgl1, libopengl0: without them sid's Blender 5.2 finds no OpenGL) and
# Vulkan (lavapipe) software drivers, for both GPU backends; python3-cattr and python3-requests,
# which Blender's own extension add-on imports at start (Debian's package does not pull them in);
# pytest and hypothesis for the core's tests on Debian's Python.
PACKAGES=(blender python3-numpy libgl1-mesa-dri libegl-mesa0 libegl1 libgl1 libopengl0 libglx-mesa0
          mesa-vulkan-drivers libvulkan1 python3-cattr python3-requests python3-pytest python3-hypothesis)
MARKER=".vpffd-blender-chroot"
export PATH="/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin:${PATH:-}"

T0=$(date +%s)
log() { echo "make_blender_chroot: [$(( $(date +%s) - T0 ))s] $*" >&2; }
die() { local code="$1"; shift; echo "make_blender_chroot: ERROR: $*" >&2; exit "$code"; }

[ "$#" -eq 1 ] && [ -n "$1" ] || die 2 "usage: $0 DIR"
[ "$(id -u)" -eq 0 ] || die 3 "must run as root (debootstrap and chroot need it)"
command -v chroot >/dev/null || die 1 "the 'chroot' command is missing (coreutils)"

mkdir -p "$(dirname "$1")"
DIR="$(cd "$(dirname "$1")" && pwd -P)/$(basename "$1")"
[ "$DIR" != "/" ] || die 2 "refusing to use / as the chroot"

# Commands inside the chroot get a clean environment (no host PYTHONPATH, venv, locale, ...).
in_chroot() {
    env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 \
        DEBIAN_FRONTEND=noninteractive \
        ${http_proxy:+http_proxy="$http_proxy"} ${https_proxy:+https_proxy="$https_proxy"} \
        chroot "$DIR" "$@"
}

blender_works() {
    [ -x "$DIR/usr/bin/blender" ] || return 1
    local out
    out=$(in_chroot blender -b --factory-startup \
          --python-expr "import bpy, numpy; print('VPFFD_BLENDER_VERSION', bpy.app.version_string)" \
          2>/dev/null) || return 1
    grep -q '^VPFFD_BLENDER_VERSION ' <<<"$out" || return 1
    sed -n 's/^VPFFD_BLENDER_VERSION //p' <<<"$out" | head -n 1
}

# Mounts below DIR would make `rm -rf DIR` dangerous; we never create any, so refuse if any exist.
mounts_below() { findmnt -rn -o TARGET 2>/dev/null | awk -v d="$DIR" 'index($0, d "/") == 1 || $0 == d'; }

# One builder at a time (parallel test runs wait here and then reuse the result).
exec 9>"$DIR.lock"
if ! flock -n 9; then
    log "another process is building $DIR, waiting for it ..."
    flock 9
fi

if version=$(blender_works); then
    missing=()   # a chroot made before a package joined PACKAGES gets it now
    for pkg in "${PACKAGES[@]}"; do
        in_chroot dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" ||
            missing+=("$pkg")
    done
    if [ "${#missing[@]}" -gt 0 ]; then
        log "adding ${missing[*]} to $DIR ..."
        { in_chroot apt-get update -q && in_chroot apt-get install -y -q --no-install-recommends \
              "${missing[@]}" && in_chroot apt-get clean; } >&2 || die 1 "apt-get inside the chroot failed"
        rm -rf "$DIR"/var/lib/apt/lists/* "$DIR"/var/cache/apt/*.bin
    fi
    log "reusing $DIR (Blender $version)"
    exit 0
fi

if [ -e "$DIR" ]; then
    [ -z "$(mounts_below)" ] || die 1 "$DIR has mounts below it ($(mounts_below | tr '\n' ' ')); unmount them first"
    if [ -f "$DIR/$MARKER" ] || [ -z "$(ls -A "$DIR" 2>/dev/null)" ]; then
        log "removing the broken or unfinished chroot at $DIR"
        rm -rf --one-file-system "$DIR"
    else
        die 1 "$DIR exists but is not a working Blender chroot made by this script; remove it or pick another DIR"
    fi
fi

# The host's debootstrap.
if ! command -v debootstrap >/dev/null; then
    command -v apt-get >/dev/null || die 4 "debootstrap is missing and there is no apt-get to install it"
    log "installing debootstrap on the host with apt-get ..."
    if ! { apt-get install -y -q --no-install-recommends debootstrap >&2 ||
           { apt-get update -q >&2 && apt-get install -y -q --no-install-recommends debootstrap >&2; }; }; then
        die 4 "could not install debootstrap with apt-get"
    fi
    command -v debootstrap >/dev/null || die 4 "debootstrap still missing after apt-get install"
fi
SCRIPT=""
if [ ! -e "/usr/share/debootstrap/scripts/$SUITE" ] && [ -e /usr/share/debootstrap/scripts/sid ]; then
    SCRIPT=/usr/share/debootstrap/scripts/sid   # old debootstrap that does not know the suite yet
fi

# Build in a scratch directory next to DIR, then rename: DIR is either complete or absent.
WORK="$DIR.partial"
if [ -e "$WORK" ]; then
    [ -z "$(DIR="$WORK" mounts_below)" ] || die 1 "$WORK has mounts below it; unmount them first"
    rm -rf --one-file-system "$WORK"
fi
mkdir -p "$WORK"
touch "$WORK/$MARKER"
trap 'log "failed; leaving $WORK for inspection (it is removed on the next run)"' ERR

log "debootstrap --variant=minbase $SUITE $WORK $MIRROR ..."
debootstrap --variant=minbase "$SUITE" "$WORK" "$MIRROR" ${SCRIPT:+"$SCRIPT"} >"$WORK.debootstrap.log" 2>&1 || {
    tail -n 20 "$WORK.debootstrap.log" >&2
    die 1 "debootstrap failed (full log: $WORK.debootstrap.log)"
}
rm -f "$WORK.debootstrap.log"
log "base system ready ($(du -sh --one-file-system "$WORK" | cut -f1))"

DIR="$WORK"
# Host network settings for apt inside the chroot: DNS and any apt proxy / validity settings.
cp -L /etc/resolv.conf "$DIR/etc/resolv.conf" 2>/dev/null || true
if command -v apt-config >/dev/null; then
    apt-config dump 2>/dev/null |
        grep -E '^Acquire::(https?|ftp)::Proxy|^Acquire::Check-(Valid-Until|Date) ' \
        >"$DIR/etc/apt/apt.conf.d/00vpffd-host" || true
fi
printf 'APT::Install-Recommends "false";\nAPT::Install-Suggests "false";\n' \
    >"$DIR/etc/apt/apt.conf.d/00vpffd-norecommends"
# Never start services inside the chroot.
printf '#!/bin/sh\nexit 101\n' >"$DIR/usr/sbin/policy-rc.d"
chmod 755 "$DIR/usr/sbin/policy-rc.d"

log "apt-get install --no-install-recommends ${PACKAGES[*]} ..."
{ in_chroot apt-get update -q && in_chroot apt-get install -y -q --no-install-recommends "${PACKAGES[@]}"; } \
    >"$WORK.apt.log" 2>&1 || {
    tail -n 30 "$WORK.apt.log" >&2
    die 1 "apt-get inside the chroot failed (full log: $WORK.apt.log)"
}
grep -E '^(Need to get|After this operation)' "$WORK.apt.log" | sed 's/^/make_blender_chroot:   /' >&2 || true
rm -f "$WORK.apt.log"
in_chroot apt-get clean
rm -rf "$DIR"/var/lib/apt/lists/* "$DIR"/var/cache/apt/*.bin

version=$(blender_works) || {
    in_chroot blender -b --factory-startup --python-expr "import bpy, numpy" >&2 || true
    die 1 "blender was installed but does not start inside the chroot"
}
[ -z "$(mounts_below)" ] || die 1 "unexpected mounts left below $DIR: $(mounts_below | tr '\n' ' ')"

FINAL="${WORK%.partial}"
mv "$WORK" "$FINAL"
DIR="$FINAL"
trap - ERR
log "done: Blender $version in $DIR ($(du -sh --one-file-system "$DIR" | cut -f1))"
