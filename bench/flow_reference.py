"""What a velocity field without turbulence can score at best: the truth's own axisymmetric mean.

Issue 23 asks for a velocity end-point error of half the zero-velocity baseline. Every model the
product has (particles in a column, the air grid, entrainment) predicts a mean flow around the
plume's axis, while the truth also swirls sideways in eddies no single view pins down. This
reference takes the truth's own velocities and keeps only what an axisymmetric flow can hold:
each sample gets the mean, over its ring, of the truth's radial, upward and swirl components. A
ring is one layer along up (`cell` thick) and one annulus (`cell` wide) around the layer's smoke
centroid, so `cell` is the resolution of the model it stands for (the bench passes the scene's
kernel radius). A model with the mean flow exactly right and no eddies would score this end-point
error; one that matches the truth's asymmetric motion may score below it.
"""

from __future__ import annotations

import numpy as np


def axisymmetric_mean_flow(points: np.ndarray, velocities: np.ndarray, up: np.ndarray, cell: float) -> np.ndarray:
    """(N, 3) each sample's ring mean of the truth's flow in cylindrical components.

    points: (N, 3) sample positions; velocities: (N, 3) the truth there; up: (3,) the plume's axis
    direction; cell: ring thickness and width (world units, > 0). A sample on the axis itself has
    no radial direction: it keeps the ring's upward mean only and leaves the ring's radial and
    swirl means to the samples around it.
    """
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive finite length, got {cell!r}")
    if len(points) == 0:
        return np.zeros((0, 3))
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    points, velocities = np.asarray(points, np.float64), np.asarray(velocities, np.float64)
    height = points @ up
    layer = np.floor((height - height.min()) / cell).astype(np.int64)
    across = points - height[:, None] * up
    counts = np.bincount(layer)
    centroid = np.stack([np.bincount(layer, across[:, k], len(counts)) for k in range(3)], axis=1)
    offset = across - centroid[layer] / np.maximum(counts[layer], 1)[:, None]
    radius = np.linalg.norm(offset, axis=1)
    radial = np.where(radius[:, None] > 0, offset / np.maximum(radius, 1e-300)[:, None], 0.0)
    swirl = np.cross(up, radial)
    frame = (radial, np.broadcast_to(up, radial.shape), swirl)
    ring = layer * (int(radius.max() // cell) + 1) + np.floor(radius / cell).astype(np.int64)
    _, ring = np.unique(ring, return_inverse=True)
    off_axis = (radius > 0).astype(np.float64)
    mean = np.zeros_like(points)
    for axis, counted in zip(frame, (off_axis, np.ones_like(off_axis), off_axis), strict=True):
        component = np.einsum("ij,ij->i", velocities, axis) * counted
        members = np.bincount(ring, counted)
        mean += (np.bincount(ring, component) / np.maximum(members, 1))[ring][:, None] * axis
    return mean
