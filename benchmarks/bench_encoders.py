"""The generator's per-sample encoders (:mod:`synth.dataset.format`) against the alternatives installed in the
environment: time per image, size and whether each round-trips exactly (issue 34).

The inputs are real samples: the first ``--samples`` of the first shard of ``--dataset`` (a folder
made by ``synth generate``), decoded with :func:`synth.dataset.format.decode_sample`, so the images,
labels, depth and correspondences have the statistics the generator's encoders see.

Per field, every encoder is first run once on every input: its bytes are decoded and compared with
the input (exactly: arrays bit for bit, a label image's palette, JSON by value), it is run a second
time to check that its bytes are deterministic (the format promises the same bytes for the same
arrays), and its bytes are compared with the current encoder's. An encoder that fails any of the
first three checks is reported as not round-tripping and is never the field's winner. Then all
encoders are timed in ``--reps`` rounds, interleaved (each round in a rotated order, so machine
noise is shared); a round's value is the mean over the inputs, the table gives the median over
rounds of wall time and of process CPU time (all threads: OpenImageIO's EXR writer uses a pool).

Alternatives: Pillow at other ``compress_level`` s and with the ``Z_RLE`` strategy; OpenImageIO's
PNG writer (``png:compressionLevel``; files only, through ``/dev/shm`` as ``encode_exr`` does);
kornia_rs (files only, no level); Mitsuba's ``Bitmap`` (in memory, PNG level 1-9, EXR PIZ); a
PNG written here with numpy filters and stdlib ``zlib`` (with Pillow's per-row filter choice it
gives Pillow's bytes exactly); OpenImageIO EXR compressions; ``zlib`` without the gzip header and
``np.savez_compressed`` for arrays. OpenImageIO, kornia_rs and Mitsuba write no palette, so they
cannot write the ``parts`` and ``bones`` label images (``mask`` is mode ``L``, no palette). The
``np.save`` rows of ``depth.exr`` are another file format, shown for scale only.

    python benchmarks/bench_encoders.py [--dataset out/demo/dataset] [--samples 16] [--reps 25]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import datetime
import gzip
import io
import os
import platform
import statistics
import struct
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import PIL
from PIL import Image
from report import write_section  # benchmarks/report.py (run as a script)

from synth.dataset import format as fmt
from synth.dataset.shards import read_shard

SIZE_SLACK = 1.10  # the size-bounded pick: at most 10 % larger than the current encoder's bytes
_SHM = "/dev/shm" if os.access("/dev/shm", os.W_OK) else None

FIELDS = {  # field: (array key, palette)
    "rgb.png": ("rgb", None),
    "mask.png": ("mask", None),
    "parts.png": ("parts", fmt.PART_PALETTE),
    "bones.png": ("bones", fmt.BONE_PALETTE),
    "depth.exr": ("depth", None),
    "corr.npy.gz": ("corr", None),
    "json": ("json", None),
}


@dataclass
class Encoder:
    field: str
    name: str
    encode: Callable[[Any], bytes]
    decode: Callable[[bytes], Any]
    current: bool = False
    reference: bool = False  # shown for scale only, never the winner (another file format)
    status: str = "yes"
    same_bytes: bool = False
    kib: float = 0.0
    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)


# ------------------------------------------------------------------------------------------------
# Encoders


def _via_file(suffix: str, write: Callable[[str], None]) -> bytes:
    """Bytes of the file ``write(path)`` makes, in a temporary file (in /dev/shm), as ``encode_exr``."""
    fd, tmp = tempfile.mkstemp(suffix=suffix, dir=_SHM)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            return f.read()
    finally:
        os.unlink(tmp)


def _pil_png(image: np.ndarray, palette: np.ndarray | None, level: int, strategy: int = -1) -> bytes:
    """``fmt.encode_png`` with another ``compress_level`` / zlib strategy."""
    img = Image.fromarray(image)
    if palette is not None:
        img = Image.fromarray(image, mode="L").convert("P")
        img.putpalette(palette.reshape(-1).tolist())
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=level, compress_type=strategy)
    return buf.getvalue()


def _oiio_write(path: str, array: np.ndarray, spec: Any) -> None:
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise RuntimeError(f"OpenImageIO cannot write {path}: {oiio.geterror()}")
    out.write_image(array)
    out.close()


def _oiio_png(image: np.ndarray, level: int) -> bytes:
    h, w = image.shape[:2]
    spec = oiio.ImageSpec(w, h, 1 if image.ndim == 2 else image.shape[2], "uint8")
    spec.attribute("png:compressionLevel", level)
    arr = image[..., None] if image.ndim == 2 else image
    return _via_file(".png", lambda p: _oiio_write(p, arr, spec))


def _oiio_exr(depth: np.ndarray, compression: str) -> bytes:
    """``fmt.encode_exr`` with another OpenEXR compression."""
    spec = oiio.ImageSpec(depth.shape[1], depth.shape[0], 1, "float")
    spec.channelnames = ("Z",)
    spec.attribute("compression", compression)
    spec.attribute("DateTime", "1970:01:01 00:00:00")
    return _via_file(".exr", lambda p: _oiio_write(p, depth[..., None], spec))


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_filter(x: np.ndarray, bpp: int, kind: str) -> np.ndarray:
    """(H, 1 + row bytes) uint8 scanlines with their filter byte from (H, row bytes) ``x``: none (0),
    up (2), paeth (4) or Pillow's choice per row (``ZipEncode.c``: of none, up, sub, paeth in that
    order the first of least sum of |signed bytes|; average is tried only with ``optimize``)."""
    h = x.shape[0]
    if kind == "none":
        filt, rows = np.zeros(h, np.uint8), x
    else:
        a = np.zeros_like(x)
        a[:, bpp:] = x[:, :-bpp]
        b = np.zeros_like(x)
        b[1:] = x[:-1]
        if kind == "up":
            filt, rows = np.full(h, 2, np.uint8), x - b
        else:
            c = np.zeros_like(x)
            c[1:, bpp:] = x[:-1, :-bpp]
            ai, bi, ci = a.astype(np.int16), b.astype(np.int16), c.astype(np.int16)
            pa, pb, pc = np.abs(bi - ci), np.abs(ai - ci), np.abs(ai + bi - 2 * ci)
            paeth = x - np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
            if kind == "paeth":
                filt, rows = np.full(h, 4, np.uint8), paeth
            else:
                cand = np.stack([x, x - b, x - a, paeth])  # Pillow's order: none, up, sub, paeth
                cost = np.abs(cand.view(np.int8).astype(np.int16)).sum(-1, dtype=np.int32)  # (4, H)
                pick = cost.argmin(0)  # the first of the least: Pillow keeps a filter only if smaller
                filt = np.array([0, 2, 1, 4], np.uint8)[pick]
                rows = cand[pick, np.arange(h)]
    out = np.empty((h, 1 + x.shape[1]), np.uint8)
    out[:, 0] = filt
    out[:, 1:] = rows
    return out


def _numpy_png(image: np.ndarray, palette: np.ndarray | None, kind: str, level: int = 1) -> bytes:
    """A PNG written here with numpy and stdlib zlib, laid out as Pillow does: a palette of at most
    16 colours packs 1, 2 or 4 bits a pixel; zlib ``memLevel`` 9. ``kind`` "pillow": Pillow's
    filters (none for an 8-bit palette image, else its per-row choice), so the bytes can match."""
    h, w = image.shape[:2]
    color = 2 if image.ndim == 3 else (3 if palette is not None else 0)
    bits = 8
    if palette is not None and len(palette) <= 16:
        bits = 1 if len(palette) <= 2 else 2 if len(palette) <= 4 else 4
    x = image.reshape(h, -1)
    if bits < 8:  # pack: the first pixel in the high bits
        per = 8 // bits
        x = np.pad(x, ((0, 0), (0, -w % per)))
        packed = x[:, 0::per] << (8 - bits)
        for k in range(1, per):
            packed |= x[:, k::per] << (8 - bits - k * bits)
        x = packed
    if kind == "pillow":
        kind = "none" if palette is not None and bits == 8 else "adaptive"
    parts = [b"\x89PNG\r\n\x1a\n", _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, color, 0, 0, 0))]
    if palette is not None:
        parts.append(_chunk(b"PLTE", np.ascontiguousarray(palette, np.uint8).tobytes()))
    z = zlib.compressobj(level, zlib.DEFLATED, 15, 9)
    raw = _png_filter(x, image.shape[2] if image.ndim == 3 else 1, kind)
    parts.append(_chunk(b"IDAT", z.compress(raw.tobytes()) + z.flush()))
    parts.append(_chunk(b"IEND", b""))
    return b"".join(parts)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def _npz(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, a=array)
    return buf.getvalue()


def _npy_gz(array: np.ndarray, level: int) -> bytes:
    return gzip.compress(_npy(array), compresslevel=level, mtime=0)


def _un_npy(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


def _un_npz(data: bytes) -> np.ndarray:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return z["a"]


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError:
        return None
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi


def _mi_png(mi: Any, image: np.ndarray, level: int) -> bytes:
    ms = mi.MemoryStream()
    mi.Bitmap(image).write(ms, mi.Bitmap.FileFormat.PNG, level)  # image: writable, C order
    return bytes(ms.raw_buffer())


def _mi_exr(mi: Any, depth: np.ndarray) -> bytes:
    ms = mi.MemoryStream()
    bmp = mi.Bitmap(depth[..., None], mi.Bitmap.PixelFormat.MultiChannel, ["Z"])
    bmp.write(ms, mi.Bitmap.FileFormat.OpenEXR, -1)  # -1: lossless PIZ
    return bytes(ms.raw_buffer())


def _kornia_png(kr: Any, image: np.ndarray) -> bytes:
    arr = image if image.ndim == 3 else np.ascontiguousarray(image[..., None])
    mode = "rgb" if image.ndim == 3 else "mono"
    return _via_file(".png", lambda p: kr.io.write_image_png_u8(p, arr, mode))


def encoders() -> list[Encoder]:
    mi = _mitsuba()
    try:
        import kornia_rs as kr
    except ImportError:
        kr = None
    out: list[Encoder] = []
    for name, (_, pal) in FIELDS.items():
        if not name.endswith(".png"):
            continue

        def add(label: str, fn: Callable[[np.ndarray], bytes], current: bool = False, name=name) -> None:
            out.append(Encoder(name, label, fn, fmt.decode_png, current))

        add("PIL level 1 (current)", lambda x, p=pal: fmt.encode_png(x, p), True)
        for level in (0, 3, 6):
            add(f"PIL level {level}", lambda x, p=pal, lv=level: _pil_png(x, p, lv))
        add("PIL level 1, Z_RLE", lambda x, p=pal: _pil_png(x, p, 1, zlib.Z_RLE))
        for level in (0, 1, 6):
            add(f"OpenImageIO level {level} (file)", lambda x, lv=level: _oiio_png(x, lv))
        if kr is not None:
            add("kornia_rs (file)", lambda x: _kornia_png(kr, x))
        if mi is not None:
            for level in (1, 5):
                add(f"Mitsuba Bitmap level {level}", lambda x, lv=level: _mi_png(mi, x, lv))
        for kind in ("none", "up", "paeth", "pillow"):
            label = "numpy+zlib 1, Pillow's filters" if kind == "pillow" else f"numpy+zlib 1, filter {kind}"
            add(label, lambda x, p=pal, k=kind: _numpy_png(x, p, k))

    def add_arr(name: str, label: str, fn, dec, current: bool = False, reference: bool = False) -> None:
        out.append(Encoder(name, label, fn, dec, current, reference))

    add_arr("depth.exr", "OpenImageIO zip (current)", fmt.encode_exr, fmt.decode_exr, True)
    for comp in ("zip:1", "zips", "piz", "rle", "none", "pxr24"):
        add_arr("depth.exr", f"OpenImageIO {comp}", lambda x, c=comp: _oiio_exr(x, c), fmt.decode_exr)
    if mi is not None:
        add_arr("depth.exr", "Mitsuba Bitmap piz (in memory)", lambda x: _mi_exr(mi, x), fmt.decode_exr)
    add_arr("depth.exr", "np.save + gzip 1 (reference, not EXR)", lambda x: _npy_gz(x, 1), fmt.decode_npy_gz,
            reference=True)
    add_arr("depth.exr", "np.save + zlib 1 (reference, not EXR)", lambda x: zlib.compress(_npy(x), 1),
            lambda d: _un_npy(zlib.decompress(d)), reference=True)

    add_arr("corr.npy.gz", "np.save + gzip 1 (current)", fmt.encode_npy_gz, fmt.decode_npy_gz, True)
    add_arr("corr.npy.gz", "np.save + zlib 1 (no gzip header)", lambda x: zlib.compress(_npy(x), 1),
            lambda d: _un_npy(zlib.decompress(d)))
    add_arr("corr.npy.gz", "np.save + gzip 0", lambda x: _npy_gz(x, 0), fmt.decode_npy_gz)
    add_arr("corr.npy.gz", "np.save + zlib 0", lambda x: zlib.compress(_npy(x), 0),
            lambda d: _un_npy(zlib.decompress(d)))
    add_arr("corr.npy.gz", "np.save + gzip 6", lambda x: _npy_gz(x, 6), fmt.decode_npy_gz)
    add_arr("corr.npy.gz", "np.savez_compressed", _npz, _un_npz)

    add_arr("json", "json.dumps (current)", fmt.encode_json, fmt.decode_json, True)
    return out


# ------------------------------------------------------------------------------------------------
# Checks and timing


def _same(a: Any, b: Any) -> bool:
    if isinstance(b, np.ndarray):
        a = np.asarray(a)
        if a.shape != b.shape or a.dtype != b.dtype:
            return False
        return bool(np.array_equal(a.view(np.uint8), b.view(np.uint8)))  # bit for bit
    return a == b


def _check(enc: Encoder, inputs: list[Any], reference: list[bytes] | None) -> list[bytes]:
    """Encode every input; set the encoder's status (round trip, palette, determinism), size and
    whether its bytes equal the current encoder's. Returns the bytes."""
    datas = [enc.encode(x) for x in inputs]
    enc.kib = statistics.mean(len(d) for d in datas) / 1024
    problems = []
    pal = FIELDS[enc.field][1]
    for x, d in zip(inputs, datas, strict=True):
        if pal is not None:
            img = Image.open(io.BytesIO(d))
            if img.mode != "P":
                problems.append(f"palette lost (mode {img.mode})")
            elif img.getpalette()[: pal.size] != pal.reshape(-1).tolist():
                problems.append("palette differs")
        elif enc.field.endswith(".png"):
            mode = Image.open(io.BytesIO(d)).mode
            if mode != ("RGB" if np.ndim(x) == 3 else "L"):
                problems.append(f"mode {mode}")
        if not _same(enc.decode(d), x):
            problems.append("values differ")
        if enc.encode(x) != d:
            problems.append("bytes not deterministic")
    if problems:
        enc.status = "no: " + ", ".join(sorted(set(problems)))
    enc.same_bytes = reference is not None and datas == reference
    return datas


def _time_round(enc: Encoder, inputs: list[Any]) -> None:
    wall = cpu = 0.0
    for x in inputs:
        t0, c0 = time.perf_counter(), time.process_time()
        enc.encode(x)
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
    enc.wall.append(1e3 * wall / len(inputs))
    enc.cpu.append(1e3 * cpu / len(inputs))


def load_inputs(dataset: Path, count: int) -> dict[str, list[Any]]:
    shards = sorted(dataset.glob("shard-*.tar"))
    if not shards:
        raise SystemExit(f"no shard-*.tar in {dataset}: make a dataset with `synth generate` first")
    samples = read_shard(shards[0])
    keys = sorted(samples)[:count]
    arrays = [fmt.decode_sample(samples[k], k) for k in keys]
    # Writable C-order copies (PIL decodes read-only arrays; Mitsuba's Bitmap wants writable ones).
    return {name: [a[key] if key == "json" else np.array(a[key], order="C") for a in arrays]
            for name, (key, _) in FIELDS.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, default=Path("out/demo/dataset"),
                        help="a dataset folder made by `synth generate` (its first shard is read)")
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--reps", type=int, default=25, help="timed rounds (median reported)")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown section here")
    args = parser.parse_args()

    inputs = load_inputs(args.dataset, args.samples)
    n = len(inputs["rgb.png"])
    encs = encoders()
    reference: dict[str, list[bytes]] = {}
    for enc in sorted(encs, key=lambda e: not e.current):  # current first: the bytes to compare with
        datas = _check(enc, inputs[enc.field], reference.get(enc.field))
        if enc.current:
            reference[enc.field] = datas
            enc.same_bytes = True
        print(f"checked {enc.field:12s} {enc.name:36s} {enc.kib:8.1f} KiB  round-trips: {enc.status}")

    for r in range(args.reps):
        k = (r * 7) % len(encs)
        for enc in encs[k:] + encs[:k]:  # rotated order: every encoder sees the same machine noise
            _time_round(enc, inputs[enc.field])
        print(f"round {r + 1}/{args.reps}", flush=True)

    ms = {id(e): statistics.median(e.wall) for e in encs}
    cpu = {id(e): statistics.median(e.cpu) for e in encs}
    current, best, small = {}, {}, {}
    for name in FIELDS:
        rows = [e for e in encs if e.field == name]
        current[name] = next(e for e in rows if e.current)
        ok = [e for e in rows if e.status == "yes" and not e.reference]
        best[name] = min(ok, key=lambda e: ms[id(e)])
        small[name] = min((e for e in ok if e.kib <= SIZE_SLACK * current[name].kib), key=lambda e: ms[id(e)])

    header = ["| field | encoder | ms / image | CPU ms / image | KiB | round-trips | bytes as now |",
              "| --- | --- | ---: | ---: | ---: | --- | --- |"]
    table = []
    for e in encs:
        label = f"**{e.name}**" if best[e.field] is e else f"*{e.name}*" if small[e.field] is e else e.name
        table.append(f"| `{e.field}` | {label} | {ms[id(e)]:.2f} | {cpu[id(e)]:.2f} | {e.kib:.1f} | "
                     f"{e.status} | {'yes' if e.same_bytes else 'no'} |")
    print("\n".join(header + table))

    total_now = sum(ms[id(current[f])] for f in FIELDS)
    total_best = sum(ms[id(best[f])] for f in FIELDS)
    total_small = sum(ms[id(small[f])] for f in FIELDS)
    total_rgb = total_now - ms[id(current["rgb.png"])] + ms[id(small["rgb.png"])]

    def pick(chosen: dict[str, Encoder]) -> str:
        return "; ".join(f"`{f}` {chosen[f].name} ({ms[id(chosen[f])]:.2f} ms, {chosen[f].kib:.1f} KiB; "
                         f"now {ms[id(current[f])]:.2f} ms, {current[f].kib:.1f} KiB)" for f in FIELDS)

    slack = f"{100 * (SIZE_SLACK - 1):.0f} %"
    summary = [
        f"Fastest round-tripping encoder per field (bold in the table): {pick(best)}.",
        "",
        f"Fastest round-tripping encoder at most {slack} larger than the current one (italic in the "
        f"table where it differs): {pick(small)}.",
        "",
        f"Total encode time per sample: {total_now:.2f} ms with the current encoders, "
        f"{total_best:.2f} ms with the fastest round-tripping ones ({total_now / total_best:.2f}x), "
        f"{total_small:.2f} ms with the fastest at most {slack} larger ({total_now / total_small:.2f}x), "
        f"{total_rgb:.2f} ms changing only `rgb.png` to the latter (every label file byte-identical).",
    ]
    print("\n" + "\n".join(summary))

    if args.out is not None:
        versions = [f"Pillow {PIL.__version__}", f"OpenImageIO {oiio.__version__}",
                    f"numpy {np.__version__}", f"zlib {zlib.ZLIB_RUNTIME_VERSION}"]
        mi = _mitsuba()
        if mi is not None:
            versions.append(f"Mitsuba {mi.__version__}")
        lines = [
            f"Measured {datetime.date.today().isoformat()} on {platform.machine()} ({os.cpu_count()} "
            f"cores), {', '.join(versions)}; {n} real samples ({args.dataset.name}, "
            f"{inputs['rgb.png'][0].shape[1]}x{inputs['rgb.png'][0].shape[0]}); "
            f"per image the median over {args.reps} interleaved rounds of the mean over the samples. "
            "CPU counts every thread of the process. Round-trips: decoded bit for bit equal, palette "
            "kept, same bytes on a second call; only encoders that round-trip can win. `bytes as now`: "
            "identical bytes to the current encoder (a label file that changes breaks reproducing "
            "a dataset byte for byte from its seed). `(file)`: the library writes files only, so a "
            "temporary file in /dev/shm is written and read, as `encode_exr` does. `numpy+zlib`: a PNG "
            "written in the script (numpy filters, stdlib zlib level 1); with Pillow's filter choice "
            "its bytes are Pillow's.",
            "",
            *header,
            *table,
            "",
            *summary,
            "",
        ]
        command = f"`python benchmarks/bench_encoders.py --dataset {args.dataset} --out {args.out}`"
        write_section(args.out, "encoders", "Sample encoders (CPU)", "benchmarks/bench_encoders.py", lines,
                      command=command)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
