"""Jacobi fields of a piece of rod (`_bvp/_variations.py`) against central differences of
adaptive `solve_static` solves, and the shooting flow's Jacobian built from them against
`jax.jvp` of the adaptive Lie-group integration."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod
from helixrod._bvp._options import BoundaryValueOptions
from helixrod._bvp._shooting import STEERING_STEPS_PER_RADIAN, flow_jacobian
from helixrod._bvp._variations import MIN_STEPS, flow_variations, piece_variations, variation_steps
from helixrod._lie import vee


@pytest.mark.parametrize("law", ["linear", pytest.param("quartic", marks=pytest.mark.heavy)])
def test_piece_variations_are_the_derivatives_of_the_flow(law):
    """The Jacobi fields of one piece (`piece_variations`, fixed Runge--Kutta steps) against
    central differences of adaptive `solve_static` solves at tolerance 1e-12: the end
    position, frame and moment, and their variations along the six start wrenches, for an
    anisotropic rod with bend-twist coupling and intrinsic curvature and for a nonlinear
    strain energy (its inverse law solved by Newton's method); and the shooting flow's
    derivatives built from them at `variation_steps` (`flow_variations`: the end position,
    frame, director-frame force and moment, as `_shooting.piece_flow` lays them out)."""
    if law == "linear":
        rod = helixrod.Rod(1.0, 1.6, 0.9, K13=0.2, K23=-0.1, uhat=(0.3, 0.0, 0.5))
    else:
        energy = lambda v: 0.5 * (v[0] ** 2 + 1.5 * v[1] ** 2 + 0.8 * v[2] ** 2) + 0.1 * v[0] ** 4  # noqa: E731
        rod = helixrod.StrainEnergyRod(energy, uhat=(0.3, 0.0, 0.5))
    wrench = np.array([0.3, -0.5, 1.2, 0.4, 0.2, -0.3])
    length = 1.3
    ours = piece_variations(rod, jnp.asarray(wrench[:3]), jnp.asarray(wrench[3:]), length, 200)

    flow = np.asarray(eqx.filter_jit(flow_variations)(rod, jnp.asarray(wrench), length, BoundaryValueOptions().max_ode_steps))

    def end(w):
        """The end position, frame (row-major), director-frame force and moment: the flow."""
        sol = helixrod.solve_static(rod, w[:3], w[3:], length, outputs=("frame", "centreline"), rtol=1e-12, atol=1e-12)
        return np.concatenate([sol.x[-1], sol.frame[-1].reshape(-1), sol.n[-1], sol.m[-1]])

    centre = end(wrench)
    x, frame = centre[:3], centre[3:12].reshape(3, 3)
    np.testing.assert_allclose(np.asarray(ours.position), x, atol=1e-10)
    np.testing.assert_allclose(np.asarray(ours.frame), frame, atol=1e-10)
    np.testing.assert_allclose(np.asarray(ours.moment), wrench[3:] - np.cross(x, wrench[:3]), atol=1e-10)
    step = 1e-5
    for j in range(6):
        difference = (end(wrench + step * np.eye(6)[j]) - end(wrench - step * np.eye(6)[j])) / (2 * step)
        rotation = np.asarray(vee(jnp.asarray(difference[3:12].reshape(3, 3) @ frame.T)))
        np.testing.assert_allclose(np.asarray(ours.d_position[:, j]), difference[:3], atol=1e-7)
        np.testing.assert_allclose(np.asarray(ours.d_rotation[:, j]), rotation, atol=1e-7)
        np.testing.assert_allclose(flow[j], difference, atol=1e-6)


@pytest.mark.heavy
def test_flow_variations_are_the_jvp_of_the_adaptive_flow():
    """`flow_variations` (Jacobi fields, equal RK4 steps at `STEPS_PER_RADIAN`) against the
    derivatives of the shooting flow by `jax.jvp` through the adaptive Lie-group integration
    at tolerance 1e-12 (`_shooting.flow_jacobian`), every one of its 18 outputs (end
    position, frame, director-frame force and moment) along the six start wrenches: the
    accuracy of the stability test's fields (~1e-7 relative), and of the coarser ones that
    steer the root finder (`STEERING_STEPS_PER_RADIAN`: ~1e-5)."""
    rod = helixrod.Rod(1.0, 1.6, 0.9, K13=0.2, K23=-0.1, uhat=(0.3, 0.0, 0.5))
    options = BoundaryValueOptions()
    ours_of = jax.jit(lambda w, length: flow_variations(rod, w, length, options.max_ode_steps))
    steering_of = jax.jit(lambda w, length: flow_variations(rod, w, length, options.max_ode_steps, STEERING_STEPS_PER_RADIAN))
    reference_of = jax.jit(lambda w, length: flow_jacobian((rod, length), w, options, jnp.asarray([1e-12, 1e-12])))
    for wrench, length in [((0.3, -0.5, 1.2, 0.4, 0.2, -0.3), 1.3), ((0.0, 0.2, -2.0, 1.5, -0.4, 0.7), 6.0)]:
        wrench = jnp.asarray(wrench)
        ours, reference = ours_of(wrench, length), reference_of(wrench, length)
        steering = steering_of(wrench, length)
        assert ours.shape == reference.shape == steering.shape == (6, 18)
        scale = float(jnp.max(jnp.abs(reference)))
        np.testing.assert_allclose(np.asarray(ours), np.asarray(reference), atol=3e-7 * scale)
        np.testing.assert_allclose(np.asarray(steering), np.asarray(reference), atol=5e-5 * scale)
        steps = int(variation_steps(rod, wrench[:3], wrench[3:], length, options.max_ode_steps))
        assert MIN_STEPS < steps < 1000
