"""One-way rigid coupling with spheres: the fluid never enters a sphere, the sphere ignores the fluid.

A particle found inside is moved to the surface and the normal component of its velocity
relative to the sphere is removed, so it slides along the surface (and is carried along by a
moving sphere). With no sphere, none of this runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from fluidcore.spec.physics import Sphere


@dataclass(frozen=True)
class Contact:
    """Particles that a sphere pushed out: mask (N,), outward normals (N, 3), sphere velocity (3,)."""

    inside: Tensor
    normal: Tensor
    velocity: Tensor


def push_out(positions: Tensor, spheres: Sequence[Sphere], time: float) -> tuple[Tensor, list[Contact]]:
    """Move particles inside any sphere (at `time`) onto its surface."""
    contacts = []
    for sphere in spheres:
        center = positions.new_tensor(sphere.center_at(time))
        offset = positions - center
        distance = torch.linalg.vector_norm(offset, dim=1, keepdim=True)
        # A particle exactly at the centre has no outward direction: send it up (+y).
        up = positions.new_tensor((0.0, 1.0, 0.0)).expand_as(offset)
        normal = torch.where(distance > 1e-12, offset / distance.clamp_min(1e-12), up)
        inside = distance[:, 0] < sphere.radius
        positions = torch.where(inside[:, None], center + normal * sphere.radius, positions)
        contacts.append(Contact(inside, normal, positions.new_tensor(sphere.velocity)))
    return positions, contacts


def surface_gaps(positions: Tensor, spheres: Sequence[Sphere], time: float) -> list[float]:
    """How far the particles at `positions` (N, 3), N > 0, keep from each sphere (at `time`): the
    distance from its surface to the nearest particle centre, world units (0 for one on or inside
    it). One distance per particle and sphere, so it costs less than a step."""
    if positions.shape[0] == 0:
        raise ValueError("surface_gaps needs at least one particle")
    gaps = []
    for sphere in spheres:
        distance = torch.linalg.vector_norm(positions - positions.new_tensor(sphere.center_at(time)), dim=1)
        gaps.append(max(0.0, float(distance.min()) - sphere.radius))
    return gaps


def merge(first: Sequence[Contact], second: Sequence[Contact]) -> list[Contact]:
    """Contacts of two push-outs of the same spheres: in contact if pushed by either."""
    return [Contact(a.inside | b.inside, torch.where(b.inside[:, None], b.normal, a.normal), b.velocity)
            for a, b in zip(first, second)]


def slide(velocities: Tensor, contacts: Sequence[Contact]) -> Tensor:
    """Remove the normal component of the velocity relative to the sphere for contacted particles."""
    for contact in contacts:
        relative = velocities - contact.velocity
        normal_speed = (relative * contact.normal).sum(1, keepdim=True)
        velocities = torch.where(contact.inside[:, None], velocities - normal_speed * contact.normal, velocities)
    return velocities
