#!/usr/bin/env python3
"""Renders a Kestrel dense map (--dense-out PLY: binary little endian, float x y z, uchar red green blue) to a PNG
with a pinhole camera and a z-buffer, Python standard library only (docs/dense.md's pictures).

usage: ply_to_png.py MAP.ply OUT.png [--eye X Y Z] [--yaw DEG] [--pitch DEG] [--width W] [--height H] [--f PX]
The camera looks along +z of its frame (x right, y down); --yaw turns it about the map's y axis, --pitch about x.
"""
import argparse, math, struct, sys, zlib


def read_ply(path):
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            sys.exit(f"{path}: not a PLY file")
        n, props = 0, []
        while True:
            line = f.readline()
            if not line:
                sys.exit(f"{path}: header ends without end_header")
            w = line.split()
            if w[0] == b"format" and w[1] != b"binary_little_endian":
                sys.exit(f"{path}: only binary_little_endian is read")
            if w[0] == b"element":
                n = int(w[2])
            if w[0] == b"property":
                props.append((w[1].decode(), w[2].decode()))
            if w[0] == b"end_header":
                break
        fmt = "<" + "".join({"float": "f", "double": "d", "uchar": "B"}[t] for t, _ in props)
        size = struct.calcsize(fmt)
        names = [p for _, p in props]
        data = f.read(n * size)
        if len(data) < n * size:
            print(f"{path}: {len(data) // size} of {n} vertices present (file cut short)", file=sys.stderr)
            n = len(data) // size
        pts = []
        for i in range(n):
            r = dict(zip(names, struct.unpack_from(fmt, data, i * size)))
            pts.append((r["x"], r["y"], r["z"], r.get("red", 200), r.get("green", 200), r.get("blue", 200)))
        return pts


def write_png(path, w, h, rgb):
    raw = b"".join(b"\x00" + bytes(rgb[y * w * 3:(y + 1) * w * 3]) for y in range(h))
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)) +
                chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ply")
    ap.add_argument("png")
    ap.add_argument("--eye", type=float, nargs=3, default=[0.0, 0.0, -0.8])
    ap.add_argument("--yaw", type=float, default=0.0)
    ap.add_argument("--pitch", type=float, default=0.0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--f", type=float, default=420.0)
    a = ap.parse_args()
    pts = read_ply(a.ply)
    cy, sy = math.cos(math.radians(a.yaw)), math.sin(math.radians(a.yaw))
    cp, sp = math.cos(math.radians(a.pitch)), math.sin(math.radians(a.pitch))
    W, H = a.width, a.height
    zbuf = [float("inf")] * (W * H)
    img = bytearray([255] * (W * H * 3))
    for x, y, z, r, g, b in pts:
        x, y, z = x - a.eye[0], y - a.eye[1], z - a.eye[2]
        x, z = cy * x - sy * z, sy * x + cy * z      # yaw about y
        y, z = cp * y - sp * z, sp * y + cp * z      # pitch about x
        if z < 0.1:
            continue
        u, v = int(a.f * x / z + W / 2), int(a.f * y / z + H / 2)
        s = max(1, int(a.f * 0.025 / z))  # a splat about half a 5 cm voxel wide
        for dv in range(-s, s + 1):
            for du in range(-s, s + 1):
                uu, vv = u + du, v + dv
                if 0 <= uu < W and 0 <= vv < H and z < zbuf[vv * W + uu]:
                    zbuf[vv * W + uu] = z
                    img[(vv * W + uu) * 3:(vv * W + uu) * 3 + 3] = bytes((r, g, b))
    write_png(a.png, W, H, img)
    print(f"{a.png}: {len(pts)} points")


if __name__ == "__main__":
    main()
