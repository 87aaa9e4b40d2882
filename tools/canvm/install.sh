#!/usr/bin/env bash
# Install the Debian packages the kernel guest of tools/canvm is made of (idempotent).
#
# usage: tools/canvm/install.sh    (as root, or with sudo that needs no password)
#
# Where it cannot install (no apt-get, no root and no such sudo, no package registry) it says
# so in one line and exits 0: the guest tests then skip, each naming what is missing.
#
#   qemu-system-x86   the emulator that boots the guest (KVM where it boots, else software)
#   linux-image-amd64 Debian's kernel: can, can-raw, can-bcm, can-gw, vcan, vxcan, sch_netem
#                     as modules (installing it only adds a kernel under /boot: the machine
#                     keeps booting what it boots)
#   busybox-static    the guest's /init and shell before the host's root is mounted
#   can-utils         candump, cansend, cangen: the guest tests' independent peers
#   iproute2          ip and tc: interfaces, queues and netem in the guest
#
# --no-install-recommends keeps it to what the guest uses (no firmware, no GUI); INITRD=No
# skips building an initrd for the new kernel (the guest boots an initramfs of its own).
set -euo pipefail

PACKAGES=(qemu-system-x86 linux-image-amd64 busybox-static can-utils iproute2)

case "${1:-}" in
    -h|--help) sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    "") ;;
    *) echo "install.sh: no arguments expected (got $*)" >&2; exit 2 ;;
esac
cannot() {
    echo "install.sh: cannot install ${PACKAGES[*]} here ($1): the kernel-guest tests will skip" >&2
    exit 0
}
command -v apt-get >/dev/null 2>&1 || cannot "no apt-get: not a Debian or Ubuntu host"
SUDO=""
if [[ "$(id -u)" -ne 0 ]]; then
    command -v sudo >/dev/null 2>&1 || cannot "not root and no sudo"
    sudo -n true 2>/dev/null || cannot "not root, and sudo asks for a password"
    SUDO="sudo -n"
fi
missing=()
for p in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [[ ${#missing[@]} -eq 0 ]]; then
    echo "install.sh: ${PACKAGES[*]} already installed"
    exit 0
fi
# a fresh machine may have no package lists yet: update once, only when the install needs it
APT=($SUDO env DEBIAN_FRONTEND=noninteractive INITRD=No apt-get -q -y)
if ! "${APT[@]}" install --no-install-recommends "${missing[@]}"; then
    "${APT[@]}" update || cannot "apt-get update failed"
    "${APT[@]}" install --no-install-recommends "${missing[@]}" || cannot "apt-get install failed"
fi
echo "install.sh: installed ${missing[*]}"
