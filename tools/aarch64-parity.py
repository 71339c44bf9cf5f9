#!/usr/bin/env python3
"""Compare what the x86-64 and the aarch64 shoal binaries computed from the
same inputs (`tools/aarch64 parity`, docs/aarch64.md).

    tools/aarch64-parity.py DIR

DIR holds, per architecture (x86_64, aarch64): `frames/` (the same scenes
rendered by each binary), `detect.jsonl` (`shoal detect` on the x86-64
frames, identical input for both), optionally `detect-given.jsonl` (`shoal
detect` on files given to `tools/aarch64 parity`) and `accuracy/accuracy.csv` (`shoal eval
accuracy --quick`: each binary renders, restores, detects and solves on its
own). Prints one table; exit status 1 if the binaries disagree on anything
discrete (which markers were read, which frames decoded) or if a file is
missing, 0 otherwise: the continuous differences are printed, not judged.
"""

import csv
import json
import math
import struct
import sys
import zlib
from pathlib import Path

ARCHES = ("x86_64", "aarch64")


def read_png_gray(path):
    """8-bit grey or RGB PNG (what `shoal sim render` writes) as (w, h, bytes)."""
    data = path.read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    pos, idat, w = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if depth != 8 or interlace != 0 or colour not in (0, 2):
                raise ValueError(f"{path}: only 8-bit, non-interlaced grey/RGB PNGs are read")
            channels = 1 if colour == 0 else 3
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    if w is None:
        raise ValueError(f"{path}: no IHDR")
    raw = zlib.decompress(idat)
    stride = w * channels
    out = bytearray(h * stride)
    prev = bytearray(stride)
    for y in range(h):
        f = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - channels] if i >= channels else 0
            b = prev[i]
            c = prev[i - channels] if i >= channels else 0
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                line[i] = (line[i] + pred) & 255
        out[y * stride : (y + 1) * stride] = line
        prev = line
    return w * channels, h, bytes(out)


def compare_frames(root):
    rows, ok = [], True
    names = sorted(p.name for p in (root / "x86_64" / "frames").glob("*.png"))
    if not names:
        print(f"error: no frames under {root / 'x86_64' / 'frames'}", file=sys.stderr)
        return [], False
    worst, differing, total = 0, 0, 0
    for name in names:
        other = root / "aarch64" / "frames" / name
        if not other.exists():
            print(f"error: {other} missing", file=sys.stderr)
            ok = False
            continue
        w1, h1, a = read_png_gray(root / "x86_64" / "frames" / name)
        w2, h2, b = read_png_gray(other)
        if (w1, h1) != (w2, h2):
            print(f"error: {name}: {w1}x{h1} on x86_64, {w2}x{h2} on aarch64", file=sys.stderr)
            ok = False
            continue
        d = [abs(x - y) for x, y in zip(a, b) if x != y]
        differing += len(d)
        total += len(a)
        worst = max(worst, max(d, default=0))
    rows.append(
        (
            f"renderer: {len(names)} frames (noisy and clean twins)",
            f"{differing} of {total} pixel values differ ({100.0 * differing / max(total, 1):.4f} %), "
            f"largest difference {worst} DN",
        )
    )
    return rows, ok


def detections(path):
    out = {}
    for line in path.read_text().splitlines():
        d = json.loads(line)
        if "id" not in d:
            continue
        key = (Path(d["source"]).name, d.get("frame", 0), d["codes"], d["id"])
        out[key] = d
    return out


def compare_detect(root, name="detect.jsonl", what="rendered frames"):
    a = detections(root / "x86_64" / name)
    b = detections(root / "aarch64" / name)
    ok = set(a) == set(b)
    only_a, only_b = sorted(set(a) - set(b)), sorted(set(b) - set(a))
    corner, trans, fits = 0.0, 0.0, 0
    for k in sorted(set(a) & set(b)):
        ca, cb = a[k]["corners_px"], b[k]["corners_px"]
        if len(ca) != len(cb):
            ok = False
            continue
        corner = max(corner, max(math.dist(p, q) for p, q in zip(ca, cb)))
        fits += a[k].get("corner_fit") != b[k].get("corner_fit")
        pa, pb = a[k].get("camera_from_marker"), b[k].get("camera_from_marker")
        if pa and pb:
            trans = max(trans, 1000.0 * math.dist(pa["t_m"], pb["t_m"]))
    rows = [
        (
            f"shoal detect on the same {what}: {len(a)} / {len(b)} detections (x86_64 / aarch64)",
            f"same markers: {'yes' if not only_a and not only_b else f'no ({only_a} only on x86_64, {only_b} only on aarch64)'}; "
            f"corners at most {corner:.2e} px apart, poses {trans:.2e} mm; corner fit chosen differently in {fits}",
        )
    ]
    return rows, ok


def accuracy_rows(path):
    with path.open() as f:
        return {
            (r["c_per_m"], r["distance_mm"], r["yaw_deg"], r["frame"], r["method"]): r
            for r in csv.DictReader(f)
        }


def compare_accuracy(root):
    a = accuracy_rows(root / "x86_64" / "accuracy" / "accuracy.csv")
    b = accuracy_rows(root / "aarch64" / "accuracy" / "accuracy.csv")
    ok = set(a) == set(b)
    decoded_diff, identical, compared = 0, 0, 0
    worst = {}  # method -> (distance mm, angle deg)
    for k in sorted(set(a) & set(b)):
        ra, rb = a[k], b[k]
        if (ra["decoded"], ra["pose"], ra["wrong_ids"]) != (rb["decoded"], rb["pose"], rb["wrong_ids"]):
            decoded_diff += 1
            continue
        if ra["distance_error_mm"] and rb["distance_error_mm"]:
            dd = abs(float(ra["distance_error_mm"]) - float(rb["distance_error_mm"]))
            da = abs(float(ra["angle_error_deg"]) - float(rb["angle_error_deg"]))
            compared += 1
            identical += dd == 0 and da == 0
            d0, a0 = worst.get(k[4], (0.0, 0.0))
            worst[k[4]] = (max(d0, dd), max(a0, da))
    ok &= decoded_diff == 0
    per_method = ", ".join(f"{m} {d:.1e} mm / {g:.1e}°" for m, (d, g) in sorted(worst.items()))
    rows = [
        (
            f"eval accuracy --quick (render, HOIRM, detect, PnP on each): {len(a)} trials",
            f"decoded / posed / wrong IDs differ in {decoded_diff}; errors identical to the CSV's 6 decimals "
            f"in {identical} of {compared} posed trials; largest differences of distance / angle error: {per_method}",
        )
    ]
    return rows, ok


def main():
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    root = Path(sys.argv[1])
    rows, ok = [], True
    parts = [compare_frames, compare_detect, compare_accuracy]
    if (root / "x86_64" / "detect-given.jsonl").exists():

        def compare_given(r):
            return compare_detect(r, "detect-given.jsonl", "given files")

        parts.insert(2, compare_given)
    for part in parts:
        try:
            r, good = part(root)
        except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
            print(f"error: {part.__name__}: {e}", file=sys.stderr)
            r, good = [], False
        rows += r
        ok &= good
    print("| what | x86_64 against aarch64 |")
    print("|---|---|")
    for what, result in rows:
        print(f"| {what} | {result} |")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
