"""Point cloud files: PCD (ascii, binary, binary_compressed), PLY (xyz), NPY.

Small, dependency-free readers. PCD's ``binary_compressed`` body is LZF (liblzf format) over
the fields stored one after the other (all x, then all y, ...); the decompressor is our own.
Organised clouds (HEIGHT > 1) come back as (H, W, 3) with NaN where there is no return;
unorganised ones as (n, 3). Any malformed file raises ``CloudFormatError`` naming the file.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

_PCD_TYPES = {
    ("F", 4): "<f4", ("F", 8): "<f8",
    ("I", 1): "<i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
    ("U", 1): "<u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
}
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class CloudFormatError(ValueError):
    """A point cloud file that cannot be read; the message names the file and the problem."""


def lzf_decompress(data: bytes, out_size: int) -> bytes:
    """Decode a liblzf stream (the codec of PCD ``binary_compressed``).

    Control byte c < 32: a literal run of c+1 bytes. Otherwise a back-reference of length
    (c >> 5) + 2 (length 7 continues in the next byte) at distance ((c & 31) << 8 | next) + 1.
    Runs are copied as slices; only overlapping references (distance < length) repeat a period.
    """
    out = bytearray(out_size)
    ip, op, n = 0, 0, len(data)
    while ip < n:
        c = data[ip]
        ip += 1
        if c < 32:
            length = c + 1
            if ip + length > n or op + length > out_size:
                raise ValueError(f"LZF literal run overruns at input byte {ip}")
            out[op:op + length] = data[ip:ip + length]
            ip += length
            op += length
            continue
        length = c >> 5
        if length == 7:
            if ip >= n:
                raise ValueError("LZF stream ends inside a back-reference")
            length += data[ip]
            ip += 1
        if ip >= n:
            raise ValueError("LZF stream ends inside a back-reference")
        ref = op - ((c & 0x1F) << 8) - data[ip] - 1
        ip += 1
        length += 2
        if ref < 0 or op + length > out_size:
            raise ValueError(f"LZF back-reference out of range at input byte {ip}")
        dist = op - ref
        if dist >= length:
            out[op:op + length] = out[ref:ref + length]
        else:  # overlapping: the last `dist` bytes repeat
            chunk = out[ref:op]
            reps = -(-length // dist)
            out[op:op + length] = (chunk * reps)[:length]
        op += length
    if op != out_size:
        raise ValueError(f"LZF output is {op} bytes, header says {out_size}")
    return bytes(out)


def _parse_pcd_header(raw: bytes, name: str) -> tuple[dict, int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise CloudFormatError(f"{name}: PCD header has no DATA line")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            return header, pos


def _pcd_fields(header: dict, name: str) -> tuple[list[str], np.dtype, int, int]:
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        width = int(header["WIDTH"][0])
        height = int(header.get("HEIGHT", ["1"])[0])
    except (KeyError, ValueError, IndexError) as exc:
        raise CloudFormatError(f"{name}: PCD header is missing or has a bad {exc}") from None
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise CloudFormatError(f"{name}: PCD FIELDS/SIZE/TYPE/COUNT lengths differ")
    for axis in "xyz":
        if axis not in fields:
            raise CloudFormatError(f"{name}: PCD has no '{axis}' field (fields: {fields})")
    dtype_fields = []
    for f, s, t, c in zip(fields, sizes, types, counts, strict=True):
        if (t, s) not in _PCD_TYPES:
            raise CloudFormatError(f"{name}: PCD field {f} has unsupported TYPE {t} SIZE {s}")
        dt = np.dtype(_PCD_TYPES[(t, s)])
        dtype_fields.append((f, dt, (c,)) if c > 1 else (f, dt))
    # unique names for repeated/padding fields ('_')
    seen: dict[str, int] = {}
    uniq = []
    for entry in dtype_fields:
        k = entry[0]
        seen[k] = seen.get(k, 0) + 1
        uniq.append((k if seen[k] == 1 else f"{k}__{seen[k]}",) + entry[1:])
    points = int(header.get("POINTS", [str(width * height)])[0])
    if points != width * height:
        raise CloudFormatError(f"{name}: PCD POINTS {points} != WIDTH*HEIGHT {width * height}")
    return fields, np.dtype(uniq), width, height


def _clear_errors(reader):
    """Turn any parsing slip on a malformed file into one CloudFormatError naming the file."""

    def wrapped(path, *args, **kw):
        try:
            return reader(path, *args, **kw)
        except CloudFormatError:
            raise
        except (ValueError, IndexError, KeyError, TypeError, OverflowError, struct.error) as exc:
            raise CloudFormatError(f"{path}: malformed {Path(path).suffix.lstrip('.')} file "
                                   f"({type(exc).__name__}: {exc})") from None

    wrapped.__name__, wrapped.__doc__ = reader.__name__, reader.__doc__
    return wrapped


def _read_raw(path: str | Path) -> tuple[str, bytes]:
    """The file's name (for messages) and bytes; an unreadable file is a CloudFormatError."""
    try:
        return str(path), Path(path).read_bytes()
    except OSError as exc:
        raise CloudFormatError(f"{path}: cannot read ({exc.strerror})") from None


@_clear_errors
def read_pcd(path: str | Path, keep_organised: bool = True) -> np.ndarray:
    """xyz of a PCD file: (H, W, 3) for organised clouds (NaN kept), else (n, 3) float64."""
    name, raw = _read_raw(path)
    header, body = _parse_pcd_header(raw, name)
    _, dtype, width, height = _pcd_fields(header, name)
    n = width * height
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    if kind == "ascii":
        text = raw[body:].decode("ascii", errors="replace").split()
        ncols = sum(int(np.prod(dtype[k].shape or (1,))) for k in dtype.names)
        if len(text) < n * ncols:
            raise CloudFormatError(f"{name}: ascii PCD has {len(text)} values, needs {n * ncols}")
        table = np.array(text[: n * ncols], dtype=float).reshape(n, ncols)
        cols, i = {}, 0
        for k in dtype.names:
            w = int(np.prod(dtype[k].shape or (1,)))
            cols[k] = table[:, i]
            i += w
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=-1)
    elif kind == "binary":
        need = n * dtype.itemsize
        if len(raw) - body < need:
            raise CloudFormatError(f"{name}: binary PCD body is {len(raw) - body} bytes, "
                                   f"needs {need}")
        rec = np.frombuffer(raw, dtype=dtype, count=n, offset=body)
        with np.errstate(invalid="ignore"):
            xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=-1).astype(float)
    elif kind == "binary_compressed":
        if len(raw) - body < 8:
            raise CloudFormatError(f"{name}: binary_compressed PCD has no size words")
        csize, usize = struct.unpack_from("<II", raw, body)
        if usize != n * dtype.itemsize:
            raise CloudFormatError(f"{name}: uncompressed size {usize} != {n * dtype.itemsize}")
        if usize > 90 * csize + 64:  # LZF expands at most ~88x (3 bytes per 264-byte copy)
            raise CloudFormatError(f"{name}: uncompressed size {usize} impossible for "
                                   f"{csize} compressed bytes")
        comp = raw[body + 8: body + 8 + csize]
        if len(comp) != csize:
            raise CloudFormatError(f"{name}: compressed body truncated ({len(comp)} of {csize})")
        try:
            plain = lzf_decompress(comp, usize)
        except ValueError as exc:
            raise CloudFormatError(f"{name}: {exc}") from None
        # Fields are stored column after column: field k occupies n * size_k bytes.
        cols, off = {}, 0
        for k in dtype.names:
            dt = dtype[k]
            cols[k] = np.frombuffer(plain, dtype=dt.base, count=n * max(1, dt.itemsize
                                    // dt.base.itemsize), offset=off)
            off += n * dt.itemsize
        xyz = np.stack([cols["x"][:n], cols["y"][:n], cols["z"][:n]], axis=-1).astype(float)
    else:
        raise CloudFormatError(f"{name}: unknown PCD DATA kind {kind!r}")
    if height > 1 and keep_organised:
        return xyz.reshape(height, width, 3)
    return xyz


@_clear_errors
def read_ply(path: str | Path) -> np.ndarray:
    """xyz (n, 3) of the vertex element of a PLY file (ascii or binary_little_endian)."""
    name, raw = _read_raw(path)
    if not raw.startswith(b"ply"):
        raise CloudFormatError(f"{name}: not a PLY file (no 'ply' magic)")
    end = raw.find(b"end_header")
    if end < 0:
        raise CloudFormatError(f"{name}: PLY header has no end_header")
    body = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, current = None, [], None
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            current = [tok[1], int(tok[2]), []]
            elements.append(current)
        elif tok[0] == "property" and current is not None:
            if tok[1] == "list":
                current[2].append((tok[-1], "list", tok[2], tok[3]))
            elif tok[1] in _PLY_TYPES:
                current[2].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise CloudFormatError(f"{name}: PLY property type {tok[1]!r} unknown")
    if fmt not in ("ascii", "binary_little_endian"):
        raise CloudFormatError(f"{name}: PLY format {fmt!r} not supported "
                               "(ascii, binary_little_endian)")
    if not elements or elements[0][0] != "vertex":
        raise CloudFormatError(f"{name}: PLY's first element is not 'vertex'")
    _, count, props = elements[0]
    if any(p[1] == "list" for p in props):
        raise CloudFormatError(f"{name}: PLY vertex element has list properties")
    names = [p[0] for p in props]
    for axis in "xyz":
        if axis not in names:
            raise CloudFormatError(f"{name}: PLY vertex has no '{axis}' property")
    if fmt == "ascii":
        rows = raw[body:].split(b"\n", count)[:count]  # the vertex lines; faces may follow
        if len(rows) < count:
            raise CloudFormatError(f"{name}: PLY has {len(rows)} data lines, needs {count}")
        try:
            table = np.array(b" ".join(rows).split(), dtype=float)
        except ValueError:
            raise CloudFormatError(f"{name}: PLY vertex lines are not numbers") from None
        if table.size != count * len(names):
            raise CloudFormatError(f"{name}: PLY vertex lines hold {table.size} values, "
                                   f"expected {count} x {len(names)}")
        table = table.reshape(count, len(names))
        return table[:, [names.index(a) for a in "xyz"]]
    dtype = np.dtype([(p[0], "<" + p[1]) for p in props])
    if len(raw) - body < count * dtype.itemsize:
        raise CloudFormatError(f"{name}: PLY body truncated")
    rec = np.frombuffer(raw, dtype=dtype, count=count, offset=body)
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=-1).astype(float)


def read_npy(path: str | Path) -> np.ndarray:
    """An (n, 3) or (H, W, 3) float array stored with numpy.save."""
    name = str(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:   # EOFError: empty or cut file
        raise CloudFormatError(f"{name}: cannot load as .npy ({exc or 'file ends early'})") \
            from None
    if not isinstance(arr, np.ndarray):               # an .npz archive
        arr.close()
        raise CloudFormatError(f"{name}: an .npz archive, not one .npy array")
    if arr.dtype.kind not in "biuf":
        raise CloudFormatError(f"{name}: expected numbers, got dtype {arr.dtype}")
    if arr.ndim not in (2, 3) or arr.shape[-1] != 3:
        raise CloudFormatError(f"{name}: expected (n, 3) or (H, W, 3), got shape {arr.shape}")
    return arr.astype(float)


def read_cloud(path: str | Path) -> np.ndarray:
    """Dispatch on the suffix: .pcd, .ply, .npy."""
    suffix = Path(path).suffix.lower()
    readers = {".pcd": read_pcd, ".ply": read_ply, ".npy": read_npy}
    if suffix not in readers:
        raise CloudFormatError(f"{path}: unknown cloud suffix {suffix!r} (.pcd, .ply, .npy)")
    return readers[suffix](path)


def finite_points(cloud: np.ndarray) -> np.ndarray:
    """The finite rows of a cloud as (n, 3), organised or not."""
    pts = cloud.reshape(-1, 3)
    return pts[np.all(np.isfinite(pts), axis=1)]


def write_pcd_ascii(path: str | Path, points: np.ndarray) -> None:
    """A minimal ascii PCD (x y z float), e.g. for tests and exports."""
    pts = np.asarray(points, dtype=float)
    h, w = (pts.shape[0], pts.shape[1]) if pts.ndim == 3 else (1, pts.shape[0])
    flat = pts.reshape(-1, 3)
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\n"
            f"HEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\nDATA ascii\n")
    with open(path, "w") as fh:
        fh.write(head)
        np.savetxt(fh, flat, fmt="%.7g")
