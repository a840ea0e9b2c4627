"""glTF primitives trimesh does not read as surfaces: it skips TRIANGLE_FAN (mode 6) without a word (a tank lost
its floor; a file of fans only was "not a valid GLTF"), reads points and lines as no faces, and fills
Draco-compressed geometry with zeros without DracoPy ("empty mesh"). Fans are rewritten here as TRIANGLES
(an index accessor of their triangles in a data: buffer) before trimesh reads the file; the others are one line.
"""
from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from pipeline.stage import StageError

MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES", 5: "TRIANGLE_STRIP",
         6: "TRIANGLE_FAN"}
_FAN = 6
_INDEX_DTYPE = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32}
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942


def _read(path: Path) -> tuple[dict, bytes | None] | None:
    """(JSON header, GLB binary chunk or None) of a .gltf / .glb; None when it does not parse (trimesh's
    reading and its message stand)."""
    data = path.read_bytes()
    try:
        if data[:4] != _GLB_MAGIC:
            return json.loads(data.decode("utf-8-sig")), None
        pos, header, binary = 12, None, None
        while pos + 8 <= len(data):
            size, kind = struct.unpack_from("<II", data, pos)
            chunk = data[pos + 8:pos + 8 + size]
            if kind == _JSON_CHUNK and header is None:
                header = json.loads(chunk.decode("utf-8"))
            elif kind == _BIN_CHUNK and binary is None:
                binary = chunk
            pos += 8 + size + (-size % 4)
        return (header, binary) if isinstance(header, dict) else None
    except (ValueError, UnicodeDecodeError, struct.error):
        return None


def _buffer(header: dict, i: int, path: Path, binary: bytes | None) -> bytes:
    uri = header["buffers"][i].get("uri")
    if uri is None:
        return binary or b""
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    return (path.parent / unquote(uri)).read_bytes()


def _indices(header: dict, accessor: int, path: Path, binary: bytes | None) -> np.ndarray:
    a = header["accessors"][accessor]
    dtype = np.dtype(_INDEX_DTYPE[a["componentType"]]).newbyteorder("<")
    view = header["bufferViews"][a["bufferView"]]
    data = _buffer(header, view["buffer"], path, binary)
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    return np.frombuffer(data, dtype, count=a["count"], offset=start).astype(np.int64)


def fan_triangles(fan: np.ndarray) -> np.ndarray:
    """(n - 2, 3) triangles (v0, vk, vk+1) of a fan, counter-clockwise as the fan (glTF's order)."""
    k = np.arange(1, len(fan) - 1)
    return np.stack([np.full(len(k), fan[0]), fan[k], fan[k + 1]], axis=1) if len(k) else np.zeros((0, 3), np.int64)


def prepare(path: Path) -> tuple[io.BytesIO, str] | None:
    """The file rewritten for trimesh with its fans as triangles (file object, file type), None when it needs
    no rewriting; a StageError for what cannot be a wall (Draco, points or lines)."""
    read = _read(path)
    if read is None:
        return None
    header, binary = read
    accessors = header.get("accessors") or []
    draco = "KHR_draco_mesh_compression" in (header.get("extensionsRequired") or []) or any(
        # optional Draco without an uncompressed fallback (accessors with no bufferView): trimesh reads zeros
        "KHR_draco_mesh_compression" in (prim.get("extensions") or {})
        and any(not isinstance(a, int) or a >= len(accessors) or "bufferView" not in accessors[a]
                for a in (prim.get("attributes") or {}).values())
        for mesh in header.get("meshes") or [] for prim in mesh.get("primitives") or [])
    if draco:
        raise StageError(f"{path}: Draco-compressed glTF is not supported: re-export without Draco compression")
    fans = []
    for m, mesh in enumerate(header.get("meshes") or []):
        for p, prim in enumerate(mesh.get("primitives") or []):
            mode = prim.get("mode", 4)
            name = f"mesh {m}" + (f" ({mesh['name']})" if mesh.get("name") else "") + f" primitive {p}"
            if mode == _FAN:
                fans.append((name, prim))
            elif mode not in (4, 5):
                raise StageError(f"{path}: {name} is {MODES.get(mode, f'mode {mode}')} (mode {mode}), not triangles: "
                                 "a wall needs surfaces (remove it or export it as triangles)")
    if not fans:
        return None
    try:
        tris = []
        for name, prim in fans:
            if "indices" in prim:
                fan = _indices(header, prim["indices"], path, binary)
            else:  # drawArrays: the vertices in order
                fan = np.arange(header["accessors"][prim["attributes"]["POSITION"]]["count"], dtype=np.int64)
            tris.append(fan_triangles(fan))
    except (KeyError, IndexError, TypeError, ValueError, OSError) as e:
        raise StageError(f"{path}: cannot read the TRIANGLE_FAN indices of {name} ({type(e).__name__}: {e})") from None
    blob = np.concatenate([t.reshape(-1) for t in tris]).astype("<u4").tobytes()
    buffers, views, accessors = (header.setdefault(k, []) for k in ("buffers", "bufferViews", "accessors"))
    buffers.append({"byteLength": len(blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()})
    offset = 0
    for (name, prim), t in zip(fans, tris):
        views.append({"buffer": len(buffers) - 1, "byteOffset": offset, "byteLength": 4 * t.size})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5125, "count": int(t.size), "type": "SCALAR"})
        prim["mode"], prim["indices"] = 4, len(accessors) - 1
        offset += 4 * t.size
    text = json.dumps(header).encode("utf-8")
    if binary is None:
        return io.BytesIO(text), "gltf"
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), _JSON_CHUNK) + text + struct.pack("<II", len(binary), _BIN_CHUNK) + binary \
        + b"\0" * (-len(binary) % 4)
    return io.BytesIO(_GLB_MAGIC + struct.pack("<II", 2, 12 + len(body)) + body), "glb"
