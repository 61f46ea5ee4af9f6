"""bench/flow_reference.py: the truth's axisymmetric mean flow, on fields built from rings."""

from __future__ import annotations

import numpy as np
import pytest

from bench.flow_reference import axisymmetric_mean_flow

CELL = 0.1
UP = np.array([0.0, 0.0, 2.0])  # not unit length, and not the y axis: both are the function's to handle


def _rings(layers: int = 3, radii: int = 3, angles: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples on rings around the axis x = 0.3, y = -0.2: (points, radial unit, swirl unit,
    (layer, ring) index); evenly spaced angles, so a uniform sideways flow has no ring mean."""
    k, j, a = np.meshgrid(np.arange(layers), np.arange(radii), np.arange(angles), indexing="ij")
    k, j, a = k.ravel(), j.ravel(), a.ravel()
    theta = 2 * np.pi * a / angles + 0.1 * j
    radius = (j + 0.5) * CELL
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)
    points = np.array([0.3, -0.2, 0.0]) + radius[:, None] * radial + ((k + 0.5) * CELL)[:, None] * np.array([0, 0, 1.0])
    swirl = np.cross([0.0, 0.0, 1.0], radial)
    return points, radial, swirl, np.stack([k, j], axis=1)


def test_an_axisymmetric_flow_is_its_own_ring_mean() -> None:
    points, radial, swirl, index = _rings()
    k, j = index[:, 0], index[:, 1]
    flow = (0.2 + 0.05 * k - 0.03 * j)[:, None] * np.array([0, 0, 1.0]) + (0.04 * j)[:, None] * radial - (0.02 * k)[:, None] * swirl
    np.testing.assert_allclose(axisymmetric_mean_flow(points, flow, UP, CELL), flow, atol=1e-12)


def test_eddies_and_a_sideways_drift_are_what_the_ring_mean_cannot_hold() -> None:
    points, radial, _, _ = _rings()
    mean = 0.25 * np.array([0, 0, 1.0]) + 0.05 * radial  # rising and spreading alike on every ring
    rng = np.random.default_rng(0)
    sideways = np.array([0.07, -0.04, 0.0])  # the same everywhere: its radial part averages out on a ring
    eddy = rng.normal(0.0, 0.03, points.shape)
    eddy -= axisymmetric_mean_flow(points, eddy, UP, CELL)  # leaves what no ring holds
    truth = mean + sideways + eddy
    reference = axisymmetric_mean_flow(points, truth, UP, CELL)
    np.testing.assert_allclose(reference, mean, atol=1e-12)
    error = np.linalg.norm(reference - truth, axis=1).mean()
    assert error == pytest.approx(np.linalg.norm(sideways + eddy, axis=1).mean())
    assert error < np.linalg.norm(truth, axis=1).mean()


def test_a_sample_on_the_axis_keeps_the_rings_upward_mean_only() -> None:
    points = np.array([[0.0, 0.0, 0.05], [0.01, 0.0, 0.05], [-0.01, 0.0, 0.05]])  # centroid (0, 0): the first sits on it
    flow = np.array([[0.5, 0.0, 0.3], [0.1, 0.0, 0.1], [-0.1, 0.0, 0.2]])
    reference = axisymmetric_mean_flow(points, flow, UP, CELL)
    np.testing.assert_allclose(reference[0], [0.0, 0.0, 0.2], atol=1e-12)  # mean up of the one ring (all three)
    np.testing.assert_allclose(reference[1:, 0], [0.1, -0.1], atol=1e-12)  # radial 0.1 outward on both sides


def test_no_samples_and_a_bad_cell() -> None:
    assert axisymmetric_mean_flow(np.zeros((0, 3)), np.zeros((0, 3)), UP, CELL).shape == (0, 3)
    for cell in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="cell"):
            axisymmetric_mean_flow(np.zeros((1, 3)), np.zeros((1, 3)), UP, cell)
