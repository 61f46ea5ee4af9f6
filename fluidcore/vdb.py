"""OpenVDB (.vdb) files written from dense numpy grids, without the OpenVDB library.

Why a writer of our own (docs/exports.md): OpenVDB's maintained Python binding installs only for
Debian's system Python, not for the project's virtual environment or the service images, and
tinyvdb (0.9) reads and edits .vdb files but cannot start a grid from nothing. What VFX tools
need from a smoke cache is a small part of the format, written here from OpenVDB's own
description of it (io/Archive, tree/*Node writeTopology and writeBuffers):

- file format 224 (what OpenVDB 4 to 12 write and 13 reads);
- one grid per named array, on the standard 5-4-3 tree (root, 32^3 and 16^3 internal nodes,
  8^3 leaves); only leaves holding a non-zero voxel are stored and, in them, only the non-zero
  (active) voxels: OpenVDB's active-mask compression, the one it uses for fog volumes;
- a `UniformScaleTranslateMap` transform: array voxel [i, j, k] is index coordinate (i, j, k),
  whose centre lies at `origin + (i, j, k) * voxel_size` in world units.

A (X, Y, Z) array becomes a `Tree_float_5_4_3` fog volume; a (X, Y, Z, 3) array a
`Tree_vec3s_5_4_3` grid of vectors that transform like velocities. torch-free.
"""

from __future__ import annotations

import io
import math
import struct
import uuid
from collections.abc import Mapping
from pathlib import Path

import numpy as np

FILE_VERSION = 224  # OpenVDB's OPENVDB_FILE_VERSION_MULTIPASS_IO, the newest that OpenVDB 12 reads without a warning
LIBRARY_VERSION = (10, 0)  # a library release that writes this layout (Debian's python3-openvdb)
MAGIC = 0x56444220  # "VDB " read as a little-endian integer
ACTIVE_MASK = 0x2  # per-grid compression flag: nodes store their active values only
INACTIVE_ARE_BACKGROUND = 0  # per-node flag: every inactive value is the background (zero)
LEAF, LOWER, UPPER = 3, 4, 5  # log2 of each node's width in children (the 5-4-3 tree)
LEAF_WIDTH = 1 << LEAF
LOWER_SPAN = 1 << (LOWER + LEAF)  # voxels across a lower internal node (128)
UPPER_SPAN = 1 << (UPPER + LOWER + LEAF)  # voxels across an upper internal node (4096)


def write_vdb(path: str | Path, grids: Mapping[str, np.ndarray], origin: np.ndarray, voxel_size: float) -> None:
    """Write `grids` (name -> (X, Y, Z) or (X, Y, Z, 3) array, zero = empty) to one .vdb file,
    all with the transform `origin` (3,) (world position of voxel [0, 0, 0]'s centre) and
    `voxel_size` (world units)."""
    out = io.BytesIO()
    out.write(struct.pack("<qIIIB", MAGIC, FILE_VERSION, *LIBRARY_VERSION, 1))  # 1: grid offsets follow
    out.write(str(uuid.uuid4()).encode("ascii"))  # 36 characters, no length
    out.write(_meta({}))  # file-level metadata: none
    out.write(struct.pack("<i", len(grids)))
    transform = _transform(np.asarray(origin, dtype=np.float64), float(voxel_size))
    for name, values in grids.items():
        array = np.asarray(values, dtype=np.float32)
        if not np.all(np.isfinite(array)):
            raise ValueError(f"grid {name!r} holds non-finite values")
        tree_type = _tree_type(array)
        head, body = _grid(name, array, transform)
        descriptor = _string(name) + _string(tree_type) + _string("")  # "": not an instance
        grid_pos = out.tell() + len(descriptor) + 24
        block_pos = grid_pos + len(head)
        out.write(descriptor + struct.pack("<qqq", grid_pos, block_pos, block_pos + len(body)) + head + body)
    Path(path).write_bytes(out.getvalue())


# What `write_vdb` writes besides the active values, for `max_file_bytes`: per leaf its value mask
# twice (topology, then buffers) and a flag; per internal node its child and value masks and a
# flag (an upper node also its origin); per grid its descriptor, metadata and transform (< 1 KiB).
LEAF_BYTES = 2 * (LEAF_WIDTH**3 // 8) + 1
LOWER_BYTES = 2 * ((1 << 3 * LOWER) // 8) + 1
UPPER_BYTES = 2 * ((1 << 3 * UPPER) // 8) + 1 + 12
GRID_BYTES = 1024
FILE_BYTES = 128  # magic, versions, uuid, metadata, grid count


def max_file_bytes(shape: tuple[int, int, int], value_bytes: Mapping[str, int]) -> int:
    """The most bytes `write_vdb` writes for grids of `shape` voxels, one per name in
    `value_bytes` (4 a float voxel, 12 a vec3): every voxel active, every node present. Exact
    Python ints (what a bundle declares before it is made, fluidcore.exports.plan_bundle)."""
    def nodes(span: int) -> int:
        return math.prod(-(-n // span) for n in shape)

    structure = nodes(LEAF_WIDTH) * LEAF_BYTES + nodes(LOWER_SPAN) * LOWER_BYTES + nodes(UPPER_SPAN) * UPPER_BYTES
    per_grid = [math.prod(shape) * size + structure + GRID_BYTES for size in value_bytes.values()]
    return FILE_BYTES + sum(per_grid)


def _tree_type(values: np.ndarray) -> str:
    kinds = {3: "float", 4: "vec3s"}
    if values.ndim not in kinds or (values.ndim == 4 and values.shape[3] != 3):
        raise ValueError(f"a VDB grid is (X, Y, Z) or (X, Y, Z, 3), got shape {values.shape}")
    return f"Tree_{kinds[values.ndim]}_{UPPER}_{LOWER}_{LEAF}"


def _grid(name: str, values: np.ndarray, transform: bytes) -> tuple[bytes, bytes]:
    """(compression, metadata, transform and topology; the leaves' values) of one grid."""
    vector = values.ndim == 4
    active = np.any(values != 0, axis=3) if vector else values != 0
    leaves = _leaf_origins(active)
    meta: dict[str, tuple[str, bytes]] = {
        "class": ("string", b"unknown" if vector else b"fog volume"),
        "creator": ("string", b"fluidnexus"),
        "name": ("string", name.encode()),
        "file_voxel_count": ("int64", struct.pack("<q", int(active.sum()))),
    }
    if vector:
        meta["vector_type"] = ("string", b"contravariant relative")  # velocities: rotate and scale, no translation
    if len(leaves):
        cells = np.argwhere(active)
        meta["file_bbox_min"] = ("vec3i", struct.pack("<3i", *cells.min(axis=0)))
        meta["file_bbox_max"] = ("vec3i", struct.pack("<3i", *cells.max(axis=0)))
    on, leaf_values = _leaf_blocks(values, active, leaves)
    masks = [_bits(row) for row in on]
    background = bytes(values.dtype.itemsize * (3 if vector else 1))
    head = struct.pack("<I", ACTIVE_MASK) + _meta(meta) + transform + _topology(leaves, masks, background)
    flag = struct.pack("<b", INACTIVE_ARE_BACKGROUND)
    body = b"".join(mask + flag + block[row].astype("<f4").tobytes() for mask, block, row in zip(masks, leaf_values, on))
    return head, body


def _leaf_origins(active: np.ndarray) -> np.ndarray:
    """(L, 3) index origins of the 8^3 leaves holding an active voxel, in the order OpenVDB
    writes them: depth first (upper node, lower node, leaf), each level sorted by x, then y, z."""
    padded = np.pad(active, [(0, -n % LEAF_WIDTH) for n in active.shape])
    x, y, z = (n // LEAF_WIDTH for n in padded.shape)
    blocks = padded.reshape(x, LEAF_WIDTH, y, LEAF_WIDTH, z, LEAF_WIDTH).any(axis=(1, 3, 5))
    origins = np.argwhere(blocks) * LEAF_WIDTH
    keys = [origins[:, axis] // span for span in (UPPER_SPAN, LOWER_SPAN, LEAF_WIDTH) for axis in range(3)]
    return origins[np.lexsort(keys[::-1])]


def _leaf_blocks(values: np.ndarray, active: np.ndarray, leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each leaf's active flags (L, 512) and values (L, 512) or (L, 512, 3), voxel n = 64 x + 8 y + z
    within the leaf (OpenVDB's order: z varies fastest)."""
    pad = [(0, -n % LEAF_WIDTH) for n in active.shape]
    active, values = np.pad(active, pad), np.pad(values, pad + [(0, 0)] * (values.ndim - 3))
    span = np.arange(LEAF_WIDTH)
    i, j, k = (leaves[:, axis, None, None, None] + span.reshape(shape) for axis, shape in
               enumerate([(1, -1, 1, 1), (1, 1, -1, 1), (1, 1, 1, -1)]))
    count = len(leaves)
    return active[i, j, k].reshape(count, LEAF_WIDTH**3), values[i, j, k].reshape(count, LEAF_WIDTH**3, *values.shape[3:])


def _topology(leaves: np.ndarray, masks: list[bytes], background: bytes) -> bytes:
    """The tree's structure: one buffer; the root (background zero, no tiles, its upper nodes);
    then depth first each internal node's child mask, value mask (no active tiles) and values
    (none), and each leaf's value mask."""
    uppers, upper_starts = _runs(leaves // UPPER_SPAN)
    parts = [struct.pack("<i", 1), background, struct.pack("<II", 0, len(uppers))]
    for upper, (first, last) in zip(uppers, upper_starts):
        lowers, lower_starts = _runs(leaves[first:last] // LOWER_SPAN)
        parts += [struct.pack("<3i", *(upper * UPPER_SPAN)), _internal_node(lowers % (1 << UPPER), UPPER)]
        for a, b in lower_starts:
            children = leaves[first + a : first + b] // LEAF_WIDTH % (1 << LOWER)
            parts += [_internal_node(children, LOWER), *masks[first + a : first + b]]
    return b"".join(parts)


def _runs(keys: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The distinct rows of sorted `keys` (N, 3) and the [start, end) of each one's run."""
    if not len(keys):
        return keys, []
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
    ends = np.r_[starts[1:], len(keys)]
    return keys[starts], list(zip(starts.tolist(), ends.tolist()))


def _internal_node(children: np.ndarray, log2: int) -> bytes:
    """An internal node with `children` (K, 3) (child coordinates within the node) and no tiles:
    child mask, value mask, the values flag, and no values (none is active)."""
    on = np.zeros(1 << (3 * log2), dtype=bool)
    on[(children[:, 0] << (2 * log2)) + (children[:, 1] << log2) + children[:, 2]] = True
    return _bits(on) + bytes(len(on) // 8) + struct.pack("<b", INACTIVE_ARE_BACKGROUND)


def _bits(on: np.ndarray) -> bytes:
    """A node mask as OpenVDB stores it: 64-bit little-endian words, bit n of the node in bit
    n % 64 of word n // 64 (the same bytes as numpy's little-endian bit order)."""
    return np.packbits(on, bitorder="little").tobytes()


def _transform(origin: np.ndarray, voxel_size: float) -> bytes:
    """A UniformScaleTranslateMap: translation, scale, voxel size and the three inverses the
    map stores alongside (1 / s, 1 / s^2, 1 / 2s), each a Vec3d."""
    if not (np.all(np.isfinite(origin)) and origin.shape == (3,) and voxel_size > 0):
        raise ValueError(f"a VDB transform needs a finite origin (3,) and a voxel size > 0, got {origin}, {voxel_size}")
    s = voxel_size
    vectors = [origin, *(np.full(3, v) for v in (s, s, 1 / s, 1 / s**2, 1 / (2 * s)))]
    return _string("UniformScaleTranslateMap") + np.concatenate(vectors).astype("<f8").tobytes()


def _meta(items: Mapping[str, tuple[str, bytes]]) -> bytes:
    """A metadata map: count, then name, type name, size and value of each entry (by name, as
    OpenVDB's std::map keeps them)."""
    parts = [struct.pack("<I", len(items))]
    for name in sorted(items):
        kind, value = items[name]
        parts += [_string(name), _string(kind), struct.pack("<I", len(value)), value]
    return b"".join(parts)


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data
