#!/usr/bin/env python3
"""A V4L2 client that is not Glint: raw ioctls (fcntl.ioctl), mmap and poll on a device.

    v4l2_probe.py DEVICE FOURCC WIDTH HEIGHT FRAMES [POLL_TIMEOUT_MS]

Prints one JSON object a line: the capability, the negotiated format, control checks,
then one line per dequeued frame, and how the stream ended ("done", "timeout" followed by
the non-blocking DQBUF's errno, or "gone" with the errno of the call that saw it).
Run under `glint-mock v4l2 --rig RIG -- python3 v4l2_probe.py ...`.
"""
import errno
import fcntl
import json
import mmap
import os
import select
import struct
import sys
import zlib


def ioc(direction, nr, size):
    return (direction << 30) | (size << 16) | (ord("V") << 8) | nr


def iowr(nr, size):
    return ioc(3, nr, size)


CAP_FMT = "<16s32s32s6I"
assert struct.calcsize(CAP_FMT) == 104
BUF_FMT = "<5I4x2q2I4B4s2IQ2IiI"
assert struct.calcsize(BUF_FMT) == 88
VIDIOC_QUERYCAP = ioc(2, 0, struct.calcsize(CAP_FMT))
VIDIOC_S_FMT = iowr(5, 208)
VIDIOC_REQBUFS = iowr(8, 20)
VIDIOC_QUERYBUF = iowr(9, 88)
VIDIOC_QBUF = iowr(15, 88)
VIDIOC_DQBUF = iowr(17, 88)
VIDIOC_STREAMON = ioc(1, 18, 4)
VIDIOC_STREAMOFF = ioc(1, 19, 4)
VIDIOC_G_CTRL = iowr(27, 8)
VIDIOC_S_CTRL = iowr(28, 8)
CAPTURE, MMAP = 1, 1
EXPOSURE_AUTO, EXPOSURE_ABSOLUTE = 0x009A0901, 0x009A0902


def out(**kv):
    print(json.dumps(kv), flush=True)


def cstr(b):
    return b.split(b"\0", 1)[0].decode()


def main():
    device, fourcc, width, height, frames = sys.argv[1:6]
    width, height, frames = int(width), int(height), int(frames)
    timeout_ms = int(sys.argv[6]) if len(sys.argv) > 6 else 2000
    fd = os.open(device, os.O_RDWR | os.O_NONBLOCK)

    cap = bytearray(struct.calcsize(CAP_FMT))
    fcntl.ioctl(fd, VIDIOC_QUERYCAP, cap)
    driver, card, bus, _version, caps, device_caps, _, _, _ = struct.unpack(CAP_FMT, cap)
    out(event="cap", driver=cstr(driver), card=cstr(card), bus=cstr(bus),
        caps=caps, device_caps=device_caps)

    fmt = bytearray(208)
    code = struct.unpack("<I", fourcc.ljust(4).encode())[0]
    struct.pack_into("<I4x6I", fmt, 0, CAPTURE, width, height, code, 1, 0, 0)
    fcntl.ioctl(fd, VIDIOC_S_FMT, fmt)
    (w, h, pf, field, bpl, size, colorspace, _priv, _flags, enc, quant, xfer) = \
        struct.unpack_from("<12I", fmt, 8)
    out(event="fmt", width=w, height=h, fourcc=struct.pack("<I", pf).decode(), field=field,
        bytesperline=bpl, sizeimage=size, colorspace=colorspace, ycbcr_enc=enc,
        quantization=quant, xfer_func=xfer)

    # Exposure: refused while automatic (EACCES), taken in manual mode, read back.
    ctrl = bytearray(struct.pack("<Ii", EXPOSURE_ABSOLUTE, 40))
    try:
        fcntl.ioctl(fd, VIDIOC_S_CTRL, ctrl)
        out(event="exposure_while_auto", errno=0)
    except OSError as e:
        out(event="exposure_while_auto", errno=e.errno)
    fcntl.ioctl(fd, VIDIOC_S_CTRL, bytearray(struct.pack("<Ii", EXPOSURE_AUTO, 1)))
    fcntl.ioctl(fd, VIDIOC_S_CTRL, ctrl)
    got = bytearray(struct.pack("<Ii", EXPOSURE_ABSOLUTE, 0))
    fcntl.ioctl(fd, VIDIOC_G_CTRL, got)
    out(event="exposure", value=struct.unpack("<Ii", got)[1])

    req = bytearray(struct.pack("<5I", 4, CAPTURE, MMAP, 0, 0))
    fcntl.ioctl(fd, VIDIOC_REQBUFS, req)
    count = struct.unpack("<5I", req)[0]
    maps = []
    for i in range(count):
        b = bytearray(88)
        struct.pack_into("<2I", b, 0, i, CAPTURE)
        struct.pack_into("<I", b, 60, MMAP)
        fcntl.ioctl(fd, VIDIOC_QUERYBUF, b)
        offset, length = struct.unpack_from("<QI", b, 64)
        maps.append(mmap.mmap(fd, length, mmap.MAP_SHARED, mmap.PROT_READ, offset=offset))
        fcntl.ioctl(fd, VIDIOC_QBUF, b)
    out(event="buffers", count=count)
    fcntl.ioctl(fd, VIDIOC_STREAMON, bytearray(struct.pack("<I", CAPTURE)))

    poller = select.poll()
    poller.register(fd, select.POLLIN)
    got_frames = 0
    while got_frames < frames:
        events = poller.poll(timeout_ms)
        if not events:
            b = bytearray(88)
            struct.pack_into("<2I", b, 0, 0, CAPTURE)
            struct.pack_into("<I", b, 60, MMAP)
            try:
                fcntl.ioctl(fd, VIDIOC_DQBUF, b)
                out(event="timeout", dqbuf_errno=0)
            except OSError as e:
                out(event="timeout", dqbuf_errno=e.errno)
            return
        revents = events[0][1]
        if revents & (select.POLLERR | select.POLLHUP):
            b = bytearray(88)
            struct.pack_into("<2I", b, 0, 0, CAPTURE)
            struct.pack_into("<I", b, 60, MMAP)
            try:
                fcntl.ioctl(fd, VIDIOC_DQBUF, b)
                e_no = 0
            except OSError as e:
                e_no = e.errno
            out(event="gone", revents=revents, dqbuf_errno=e_no)
            try:
                fcntl.ioctl(fd, VIDIOC_QUERYCAP, bytearray(len(cap)))
                out(event="after_gone", querycap_errno=0)
            except OSError as e:
                out(event="after_gone", querycap_errno=e.errno)
            os.close(fd)
            return
        b = bytearray(88)
        struct.pack_into("<2I", b, 0, 0, CAPTURE)
        struct.pack_into("<I", b, 60, MMAP)
        fcntl.ioctl(fd, VIDIOC_DQBUF, b)
        (index, _t, used, flags, field, sec, usec, _tct, _tcf, _f, _s, _m, _h, _u,
         seq, _mem, _off, _len, _r2, _rfd, _r) = struct.unpack(BUF_FMT, b)
        data = maps[index][:used]
        out(event="frame", index=index, sequence=seq, bytesused=used, flags=flags, field=field,
            timestamp_us=sec * 1_000_000 + usec, head=data[:4].hex(), tail=data[-2:].hex(),
            mean=sum(data[::97]) / max(1, len(data[::97])), crc=zlib.crc32(data))
        fcntl.ioctl(fd, VIDIOC_QBUF, b)
        got_frames += 1
    fcntl.ioctl(fd, VIDIOC_STREAMOFF, bytearray(struct.pack("<I", CAPTURE)))
    os.close(fd)
    out(event="done")


if __name__ == "__main__":
    try:
        main()
    except OSError as e:
        out(event="error", errno=e.errno, what=str(e))
        sys.exit(1)
