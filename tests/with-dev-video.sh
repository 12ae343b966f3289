#!/bin/sh
# with-dev-video.sh DEVICE N CMD [ARG...]: run CMD where /dev/videoN is DEVICE.
#
# nokhwa opens a V4L2 camera only as /dev/videoN (by index), while `glint-mock v4l2` makes
# its simulated camera at the path the rig names (e.g. /tmp/glint-sim-nokhwa/video0). This
# gives CMD, and CMD alone, a /dev in which videoN is a link to DEVICE: a private mount
# namespace (unshare) with a fresh tmpfs on /dev holding links to every entry of the
# machine's /dev (bound beneath it at /dev/.host) and videoN -> DEVICE. The machine's /dev is
# not touched. The preload library of `glint-mock v4l2` knows its device by the file a path
# resolves to, so opening /dev/videoN opens the simulated camera.
#
# Needs root, or unprivileged user namespaces (then `unshare --map-root-user`).
#
#   glint-mock v4l2 --rig rigs/sim-nokhwa.toml -- \
#       tests/with-dev-video.sh /tmp/glint-sim-nokhwa/video0 0 glint run --rig rigs/sim-nokhwa.toml
set -eu

if [ "$#" -lt 3 ]; then
    echo "usage: $0 DEVICE N CMD [ARG...]" >&2
    exit 2
fi

if [ "${GLINT_WITH_DEV_VIDEO:-}" != "inside" ]; then
    export GLINT_WITH_DEV_VIDEO=inside
    if [ "$(id -u)" -eq 0 ]; then
        exec unshare --mount --propagation private "$0" "$@"
    fi
    exec unshare --mount --map-root-user --propagation private "$0" "$@"
fi
unset GLINT_WITH_DEV_VIDEO

device=$1
n=$2
shift 2
case "$n" in
    ''|*[!0-9]*) echo "$0: N must be a number, not '$n'" >&2; exit 2 ;;
esac
case "$device" in
    /*) ;;
    *) device="$(pwd)/$device" ;;
esac
if [ ! -e "$device" ]; then
    echo "$0: $device does not exist (is glint-mock v4l2 running?)" >&2
    exit 1
fi

# Build the new /dev on a tmpfs mounted over /tmp for the moment (a directory every
# machine has; the real /tmp is back once the tmpfs is moved to /dev).
mount -t tmpfs -o mode=755 glint-dev /tmp
mkdir /tmp/.host
mount --rbind /dev /tmp/.host
for e in /tmp/.host/* /tmp/.host/.[!.]*; do
    [ -e "$e" ] || [ -L "$e" ] || continue
    name=${e#/tmp/.host/}
    [ "$name" = "video$n" ] && continue
    ln -s "/dev/.host/$name" "/tmp/$name"
done
ln -s "$device" "/tmp/video$n"
mount --move /tmp /dev
exec "$@"
