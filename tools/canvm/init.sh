#!/bin/busybox sh
# /init of the kernel guest that tools/canvm/canvm.py boots (busybox sh, PID 1).
#
# It loads the modules the host listed in /modules (dependency order), mounts the host's root
# read-only over virtio-9p with a tmpfs overlay on top (the guest may write anywhere, the host
# sees none of it), mounts the job's folder (the only writable share) at /run/canvm, and runs
# /run/canvm/job.sh in that root as root. PID 1 must never exit, so it powers the guest off
# itself afterwards; the kernel's panic=-1 turns any crash into a reboot, which qemu's
# -no-reboot turns into an exit.
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
echo "canvm: kernel $(uname -r) up after $(cut -d' ' -f1 /proc/uptime) s"
while read -r module; do
    [ -n "$module" ] || continue
    insmod "/lib/modules/$module" || echo "canvm: insmod $module failed"
done </modules
mkdir -p /lower /upper /root
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=512000,cache=loose hostroot /lower \
    || { echo "canvm: cannot mount the host's root"; poweroff -f; }
mount -t tmpfs -o size=75% upper /upper
mkdir -p /upper/data /upper/work
mount -t overlay -o lowerdir=/lower,upperdir=/upper/data,workdir=/upper/work overlay /root \
    || { echo "canvm: cannot mount the overlay"; poweroff -f; }
mount -t proc proc /root/proc
mount -t sysfs sys /root/sys
mount -o bind /dev /root/dev
mkdir -p /root/dev/pts /root/dev/shm
mount -t devpts devpts /root/dev/pts
mount -t tmpfs shm /root/dev/shm
mount -t tmpfs run /root/run
mkdir -p /root/run/canvm
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 canvm /root/run/canvm \
    || { echo "canvm: cannot mount the job folder"; poweroff -f; }
hostname canvm
echo "canvm: guest ready after $(cut -d' ' -f1 /proc/uptime) s"
chroot /root /bin/sh /run/canvm/job.sh
echo "canvm: job exited with $?"
sync
poweroff -f
