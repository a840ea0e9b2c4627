"""Triangulation of the polygons of a mesh file (n-gons of USD faceVertexCounts, OBJ, PLY and OFF faces).

A polygon keeps its fan from the first vertex when every fan triangle has a positive area in the
polygon's plane: for a simple polygon that is exactly when the fan is a correct triangulation (the fan
triangles' signed areas add up to the winding number, 0 or 1, so none overlap and none is missing).
Convex polygons, and concave ones whose first vertex sees all others, keep the triangles a plain fan
gave, bit for bit. Every other polygon (a reflex vertex, collinear or repeated vertices next to the
first one) is ear-clipped in its best-fit plane (Newell normal). Triangles keep the polygon's winding.
"""
from __future__ import annotations

import re

import numpy as np

# A fan triangle this small against its polygon (area ratio) counts as degenerate: left in, it is
# dropped by the clean-up and leaves a crack (a T-junction) where the polygon had a straight vertex.
FAN_TOLERANCE = 1e-12
# Ear clipping in plain Python up to this sum of squared polygon sizes (about 10 ms), numba beyond
PYTHON_WORK = 4096


def fan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) positions into the face-vertex list of the fan triangles of every face, and (T,) the
    face of each triangle."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    n_tri = counts - 2
    face_of_tri = np.repeat(np.arange(len(counts)), n_tri)
    k = np.arange(len(face_of_tri)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)  # fan index within a face
    s = starts[face_of_tri]
    return np.stack([s, s + k + 1, s + k + 2], axis=1), face_of_tri


def triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles ((T, 3) int64 indices into ``points``) of the polygons given as counts (each >= 3) and
    concatenated vertex indices, and (T,) the polygon of each triangle. Every polygon gives counts - 2
    triangles in polygon order, so each triangle's position is that of the plain fan."""
    with np.errstate(invalid="ignore", over="ignore"):  # NaN / Inf points: the callers refuse them in one line
        return _triangulate(points, counts, indices)


def _triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    counts = np.asarray(counts, np.int64)
    indices = np.asarray(indices, np.int64)
    corner, face_of_tri = fan(counts)
    tris = indices[corner]
    big = counts > 3
    if not big.any():  # a triangle mesh: nothing to decide
        return tris, face_of_tri
    points = np.asarray(points, np.float64)
    normal = newell_normals(points, counts, indices)
    # fan triangles of the n-gons: positive area in the polygon's plane?
    sel = big[face_of_tri]
    t = tris[sel]
    f = face_of_tri[sel]
    a = points[t[:, 0]]
    d = np.einsum("ij,ij->i", np.cross(points[t[:, 1]] - a, points[t[:, 2]] - a), normal[f])
    n2 = np.einsum("ij,ij->i", normal, normal)
    bad_fan = np.zeros(len(counts), bool)
    bad_fan[f[d <= FAN_TOLERANCE * n2[f]]] = True
    redo = np.nonzero(bad_fan & (n2 > 0))[0]  # no plane at all (every vertex on a line): the fan is as good as any
    if len(redo) == 0:
        return tris, face_of_tri
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rc = counts[redo]
    rs = np.concatenate([[0], np.cumsum(rc)[:-1]])
    pos = np.repeat(starts[redo] - rs, rc) + np.arange(rc.sum())  # face-vertex positions of the redone polygons
    xy = _to_plane(points[indices[pos]], normal[redo], rc)
    # (sum(rc - 2), 3) vertex numbers within each polygon; a few small polygons are quicker in plain
    # Python than loading numba and its cached kernel (about 1 s)
    clip = _ear_clip if int((rc * rc).sum()) <= PYTHON_WORK else _ear_clip_compiled()
    local = clip(xy, rs, rc)
    out_rows = np.repeat(np.cumsum(counts - 2)[redo] - (rc - 2), rc - 2) + \
        np.arange((rc - 2).sum()) - np.repeat(np.cumsum(rc - 2) - (rc - 2), rc - 2)
    tris[out_rows] = indices[np.repeat(starts[redo], rc - 2)[:, None] + local]
    return tris, face_of_tri


def newell_normals(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(F, 3) Newell normal of each polygon: twice its vector area, along the normal of the plane that
    fits it best, pointing as its winding does (right hand)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p = points[indices]
    nxt = np.arange(len(indices)) + 1
    last = starts + counts - 1
    nxt[last] = starts  # each polygon closes on its first vertex
    # about the first vertex of the polygon: no loss of digits far from the origin
    p = p - np.repeat(p[starts], counts, axis=0)
    return np.add.reduceat(np.cross(p, p[nxt]), starts, axis=0)


def _to_plane(p: np.ndarray, normal: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """2-D coordinates of each polygon's vertices in its plane, axes (u, v) with u x v along the
    normal: the polygon's winding is counter-clockwise there."""
    n = normal / np.linalg.norm(normal, axis=1)[:, None]
    axis = np.eye(3)[np.argmin(np.abs(n), axis=1)]
    u = np.cross(n, axis)
    u /= np.linalg.norm(u, axis=1)[:, None]
    v = np.cross(n, u)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    q = p - np.repeat(p[starts], counts, axis=0)
    return np.stack([np.einsum("ij,ij->i", q, np.repeat(u, counts, axis=0)),
                     np.einsum("ij,ij->i", q, np.repeat(v, counts, axis=0))], axis=1)


_EAR_CLIP = None


def _ear_clip_compiled():
    """_ear_clip compiled by numba, on first use: a mesh whose polygons all fan does not load numba
    (0.6 s)."""
    global _EAR_CLIP
    if _EAR_CLIP is None:
        import numba as nb

        _EAR_CLIP = nb.njit(cache=True)(_ear_clip)
    return _EAR_CLIP


def _ear_clip(xy, starts, counts):
    """Ear clipping of counter-clockwise 2-D polygons; (sum(counts - 2), 3) vertex numbers within each
    polygon, each triangle counter-clockwise. A polygon with no ear left (self-intersecting, or folded
    by the projection) gets its most convex corner clipped instead, so it still yields counts - 2
    triangles (possibly degenerate ones, which the clean-up drops)."""
    out = np.empty((int((counts - 2).sum()), 3), np.int64)
    row = 0
    for f in range(len(counts)):
        n = counts[f]
        m = xy[starts[f]:starts[f] + n]
        area2 = 0.0
        for i in range(n):
            j = (i + 1) % n
            area2 += m[i, 0] * m[j, 1] - m[j, 0] * m[i, 1]
        eps = FAN_TOLERANCE * abs(area2)
        prv = np.empty(n, np.int64)
        nxt = np.empty(n, np.int64)
        for i in range(n):
            prv[i] = (i - 1) % n
            nxt[i] = (i + 1) % n
        left = n
        v = 0
        while left > 3:
            found = False
            best, best_cross = v, -np.inf
            w = v
            for _ in range(left):
                p, q = prv[w], nxt[w]
                c = (m[w, 0] - m[p, 0]) * (m[q, 1] - m[p, 1]) - (m[w, 1] - m[p, 1]) * (m[q, 0] - m[p, 0])
                if c > best_cross:
                    best, best_cross = w, c
                if c > eps:
                    # an ear: no other remaining vertex inside or on the triangle (p, w, q); one at a
                    # corner of it (a polygon touching itself) does not count
                    found = True
                    r = nxt[q]
                    while r != p:
                        x, y = m[r, 0], m[r, 1]
                        corner = ((x == m[p, 0] and y == m[p, 1]) or (x == m[w, 0] and y == m[w, 1])
                                  or (x == m[q, 0] and y == m[q, 1]))
                        if (not corner
                                and (m[w, 0] - m[p, 0]) * (y - m[p, 1]) - (m[w, 1] - m[p, 1]) * (x - m[p, 0]) >= -eps
                                and (m[q, 0] - m[w, 0]) * (y - m[w, 1]) - (m[q, 1] - m[w, 1]) * (x - m[w, 0]) >= -eps
                                and (m[p, 0] - m[q, 0]) * (y - m[q, 1]) - (m[p, 1] - m[q, 1]) * (x - m[q, 0]) >= -eps):
                            found = False
                            break
                        r = nxt[r]
                    if found:
                        break
                w = nxt[w]
            if not found:
                w = best
            p, q = prv[w], nxt[w]
            out[row, 0], out[row, 1], out[row, 2] = p, w, q
            row += 1
            nxt[p] = q
            prv[q] = p
            left -= 1
            v = q
        out[row, 0], out[row, 1], out[row, 2] = prv[v], v, nxt[v]
        row += 1
    return out


# -- polygons of mesh files that trimesh fans on loading ---------------------------------------------
_OBJ_NGON = re.compile(rb"^[ \t]*f[ \t]+\S+[ \t]+\S+[ \t]+\S+[ \t]+\S", re.M)  # a face of 4 or more vertices


UTF8_BOM = b"\xef\xbb\xbf"


class ObjIndexError(ValueError):
    """A face index the OBJ file cannot mean (0, past the vertices read so far, or no number at all): the
    message names the line and is said as it is."""


def obj_lines(data: bytes):
    """(number, line) of an OBJ file's bytes, a line ending in ``\\`` joined to the next one (the OBJ spec's
    continuation: exporters wrap long faces so) and numbered as the first of the lines it joins. A UTF-8 byte
    order mark (Windows editors write one) is no part of the first line: left on, it hid that line's ``v``."""
    pending, first = b"", 0
    for number, line in enumerate(data.removeprefix(UTF8_BOM).splitlines(), 1):
        stripped = line.rstrip(b" \t")
        if stripped.endswith(b"\\"):
            if not pending:
                first = number
            pending += stripped[:-1] + b" "
            continue
        if pending:
            yield first, pending + line
            pending = b""
        else:
            yield number, line
    if pending:  # a continuation on the last line: nothing follows
        yield first, pending


def obj_index(token: bytes, number: int) -> int:
    """The vertex number of a face vertex ``a``, ``a/t``, ``a//n`` or ``a/t/n`` on line ``number``; anything
    else (a stray backslash, a word) is refused naming the line, not an int() error without one."""
    try:
        return int(token.split(b"/", 1)[0])
    except ValueError:
        raise ObjIndexError(f"line {number}: '{token.decode('utf-8', 'replace')[:40]}' is not a face vertex "
                            "(a vertex number counted from 1, as in 7, 7/2, 7//3 or 7/2/3)") from None


def obj_polygons(data: bytes, triangles_too: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vertices, counts, indices) of the faces of an OBJ file's bytes, every object and group alike; None
    when every face is a triangle (unless ``triangles_too``). Only ``v`` and ``f`` lines count, tokens split at
    any white space, ``#`` starting a comment anywhere, a line ending in ``\\`` continued on the next; a face
    vertex ``a``, ``a/t``, ``a//n`` or ``a/t/n`` is vertex ``a``, counted from 1, or when negative back from the
    last vertex read so far (the OBJ spec: streaming exporters repeat ``f -4 -3 -2 -1`` after each quad's
    vertices). Raises ObjIndexError on an index 0, out of range or not a number, naming the line."""
    if not triangles_too and _OBJ_NGON.search(data) is None:
        return None
    verts: list[list[bytes]] = []
    counts: list[int] = []
    indices: list[int] = []
    for number, line in obj_lines(data):
        tok = line.split(b"#", 1)[0].split()
        if not tok:
            continue
        if tok[0] == b"v":
            verts.append(tok[1:4])
        elif tok[0] == b"f" and len(tok) > 3:
            n_v = len(verts)
            face = [obj_index(t, number) for t in tok[1:]]
            if 0 in face:
                raise ObjIndexError(f"line {number}: face index 0 is not valid in OBJ (indices start at 1)")
            face = [i - 1 if i > 0 else n_v + i for i in face]
            if min(face) < 0 or max(face) >= n_v:
                raise ObjIndexError(f"line {number}: face index out of range in "
                                    f"{line.decode('utf-8', 'replace').strip()[:80]!r} (only {n_v} vertices defined before it)")
            counts.append(len(face))
            indices += face
    return np.array(verts, np.float64).reshape(-1, 3), np.array(counts, np.int64), np.array(indices, np.int64)


def off_polygons(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vertices, counts, indices) of an OFF file's bytes (OFF, COFF, NOFF...: the first three numbers of a
    vertex line are its position, a face line is its count and indices, colours after them ignored; ``#``
    comments); None when the file is not laid out as expected (trimesh's reading stands). Read here, not
    by trimesh, whose loader fails on a file mixing polygon sizes (quads and an L-shaped hexagon). Raises
    ValueError on an index out of range."""
    rows = [r.split() for r in (line.split(b"#", 1)[0] for line in data.splitlines()) if r.strip()]
    if not rows or not rows[0][0].endswith(b"OFF"):
        return None
    head = rows[0][1:] or (rows[1] if len(rows) > 1 else [])
    body = rows[1:] if rows[0][1:] else rows[2:]
    try:
        n_v, n_f = int(head[0]), int(head[1])
        verts = np.array([r[:3] for r in body[:n_v]], np.float64).reshape(-1, 3)
        faces = [[int(t) for t in r[1:1 + int(r[0])]] for r in body[n_v:n_v + n_f]]
    except (ValueError, IndexError):
        return None
    if len(verts) != n_v or len(faces) != n_f or any(len(f) < 3 for f in faces):
        return None
    counts = np.array([len(f) for f in faces], np.int64)
    indices = np.array([i for f in faces for i in f], np.int64)
    if len(indices) and (indices.min() < 0 or indices.max() >= n_v):
        bad = int(indices[(indices < 0) | (indices >= n_v)][0])
        raise ValueError(f"face index {bad} out of range (only {n_v} vertices)")
    return verts, counts, indices


def ply_polygons(raw: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """(counts, indices) of the faces of a PLY file as trimesh read it (``metadata["_ply_raw"]``); None
    when they are all triangles or the face list is not found."""
    face = raw.get("face") or {}
    data = face.get("data")
    if data is None or not face.get("length"):
        return None
    if isinstance(data, dict):
        data = next((data[k] for k in ("vertex_indices", "vertex_index") if k in data), None)
    elif isinstance(data, np.ndarray) and data.dtype.names:  # binary: a record per face, (count, list)
        names = [k for k in ("vertex_indices", "vertex_index") if k in data.dtype.names] or list(data.dtype.names[:1])
        data = data[names[0]]["f1"]
    if data is None:
        return None
    if isinstance(data, np.ndarray) and data.dtype != object:
        if data.ndim != 2 or data.shape[1] == 3:
            return None
        return np.full(len(data), data.shape[1], np.int64), data.reshape(-1).astype(np.int64)
    faces = [np.asarray(f, np.int64).reshape(-1) for f in data]
    counts = np.array([len(f) for f in faces], np.int64)
    if (counts == 3).all():
        return None
    return counts, np.concatenate(faces)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def ply_binary_polygons(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """(vertices, counts, indices, bytes after the data the header declares) of a binary PLY whose faces are not
    all of one size (Blender's quads and triangles: trimesh's binary reader takes every list to be as long as the
    first and refused the file as 'unexpected length'), or that has bytes after its data (padding an exporter or
    a copy added: trimesh refused that too); None for ASCII PLY, a header not understood here, or faces all of
    one size and nothing after them (trimesh reads those as before). Other vertex and face properties, before or
    after, and any list count type are skipped. Raises ValueError when the file ends before the data its header
    promises (a truncated copy), or on a face index out of range."""
    data = data.removeprefix(UTF8_BOM)
    end = data.find(b"end_header", 0, 1 << 16)
    if not data.startswith(b"ply") or end < 0:
        return None
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:end + 16] else end + len(b"end_header")
    endian = None
    elements: list[tuple[str, int, list]] = []
    try:
        for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
            w = line.split()
            if not w or w[0] in ("comment", "obj_info"):
                continue
            if w[0] == "format":
                endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(w[1])
            elif w[0] == "element":
                elements.append((w[1], int(w[2]), []))
            elif w[0] == "property" and w[1] == "list":
                elements[-1][2].append((w[4], endian + _PLY_TYPES[w[2]], endian + _PLY_TYPES[w[3]]))
            elif w[0] == "property":
                elements[-1][2].append((w[2], endian + _PLY_TYPES[w[1]], None))
    except (IndexError, KeyError, ValueError, TypeError):  # TypeError: a property before 'format'
        return None
    if endian is None or not elements:
        return None
    buf = np.frombuffer(data, np.uint8)
    found: dict[str, dict[str, tuple]] = {}
    pos = body
    for name, n, props in elements:
        if any(p[2] is not None for p in props):
            offsets, end = _ply_offsets(data, buf, pos, n, props, name)
            found[name] = {p[0]: (o, p) for p, o in zip(props, offsets)}
        else:  # a record of scalars: a view of the bytes (no offsets per property of a 10M-vertex file)
            record = np.dtype([(p[0], p[1]) for p in props]) if props else np.dtype([])
            end = pos + n * record.itemsize
            if end > len(data):
                raise _ply_cut(n, name)
            table = np.frombuffer(data, record, n, pos) if record.itemsize else None
            found[name] = {p[0]: (table, p) for p in props}
        pos = end
    vertex, face = found.get("vertex", {}), found.get("face", {})
    lists = [k for k in ("vertex_indices", "vertex_index") if k in face and face[k][1][2] is not None]
    if not all(k in vertex and vertex[k][1][2] is None for k in "xyz") or not lists:
        return None
    where, (_, count_type, item_type) = face[lists[0]]
    counts = _gather(buf, where, count_type).astype(np.int64)
    extra = len(data) - pos
    if len(counts) == 0 or ((counts == counts[0]).all() and not extra):
        return None
    counts_at = where + np.dtype(count_type).itemsize
    size = np.dtype(item_type).itemsize
    ends = np.cumsum(counts)
    items = np.repeat(counts_at, counts) + size * (np.arange(ends[-1]) - np.repeat(ends - counts, counts))
    indices = _gather(buf, items, item_type).astype(np.int64)
    verts = np.stack([vertex[k][0][k] if isinstance(vertex[k][0], np.ndarray) and vertex[k][0].dtype.names
                      else _gather(buf, vertex[k][0], vertex[k][1][1]) for k in "xyz"], axis=1).astype(np.float64)
    keep = counts >= 3  # a "face" of one or two vertices (a point or an edge) has no area: left out
    if not keep.all():
        indices, counts = indices[np.repeat(keep, counts)], counts[keep]
    if len(indices) and (indices.min() < 0 or indices.max() >= len(verts)):
        bad = int(indices[(indices < 0) | (indices >= len(verts))][0])
        raise ValueError(f"face index {bad} out of range (only {len(verts)} vertices)")
    return verts, counts, indices, extra


def _gather(buf: np.ndarray, offsets: np.ndarray, dtype: str) -> np.ndarray:
    """The values of ``dtype`` starting at byte ``offsets`` of ``buf``."""
    dt = np.dtype(dtype)
    return np.ascontiguousarray(buf[offsets[:, None] + np.arange(dt.itemsize)]).view(dt).reshape(-1)


def _ply_offsets(data: bytes, buf: np.ndarray, pos: int, n: int, props: list, name: str) -> tuple[list, int]:
    """The byte offset of each property (a list's: of its count) in each of the ``n`` records of an element with
    lists starting at ``pos``, and where the element ends. Its records differ in length: a pass over them in
    Python, unless every list has the length of the first record's (vectorised)."""
    import struct

    cut = _ply_cut(n, name)
    sizes = [np.dtype(p[1]).itemsize for p in props]
    items = [np.dtype(p[2]).itemsize if p[2] is not None else 0 for p in props]
    counts = [struct.Struct(p[1][0] + _STRUCT[p[1][1:]]).unpack_from if p[2] is not None else None for p in props]
    if n == 0:
        return [np.zeros(0, np.int64) for _ in props], pos
    # the first record's layout, and every record's were they all like it
    fixed, at = [], pos
    try:
        for s, item, count in zip(sizes, items, counts):
            fixed.append(at - pos)
            at += s + item * int(count(data, at)[0]) if item else s
    except struct.error:
        raise cut from None
    stride = at - pos
    end = pos + n * stride
    offsets = [pos + stride * np.arange(n, dtype=np.int64) + o for o in fixed]
    lists = [k for k, item in enumerate(items) if item]
    if end <= len(data) and all((_gather(buf, offsets[k], props[k][1]) == _gather(buf, offsets[k][:1], props[k][1])).all()
                                for k in lists):
        return offsets, end
    out = [[0] * n for _ in props]
    at = pos
    try:
        for r in range(n):
            for k, (s, item, count) in enumerate(zip(sizes, items, counts)):
                out[k][r] = at
                at += s + item * int(count(data, at)[0]) if item else s
    except struct.error:
        raise cut from None
    if at > len(data):
        raise cut
    return [np.array(o, np.int64) for o in out], at


def _ply_cut(n: int, name: str) -> ValueError:
    return ValueError(f"binary PLY cut off: the file ends inside its {n:,} {name} records (an interrupted download "
                      "or copy?)")


_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
