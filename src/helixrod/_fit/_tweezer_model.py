"""The forward model of tweezer data (`TweezerData`): extension (and measured torque) of
DNA molecules at their force and turns or torque, through the rod and its thermal
fluctuations (`helixrod._tweezer`).

Residuals: the predicted extensions minus the measured ones over their sigmas, then the
measured torques (where recorded) likewise; `predicted` holds the predictions, their
`phase`, `ok` per point and the `extension_sigma` used (the effective one with errors in
variables, then also `residual_sigma`, the sigma of every residual).  Besides the rod, the
model has its own
parameters: `persistence_length` (nm, free), `plectoneme_twist_persistence` (nm; free when
some point is turned, else fixed at its default) and one bead-height `offset_<molecule>`
(nm) per molecule added to its extensions (fixed at 0 unless the model option
`fit_offsets=True`).  With sigmas of the controls (force, turns) in the data, errors in
variables are on by default: the effective variance $\\sigma_h^2 + (\\partial h/\\partial F\\,
\\sigma_F)^2 + (\\partial h/\\partial n\\,\\sigma_n)^2$ of each extension (Orear, Am. J. Phys.
50, 912 (1982)), its weights held fixed in the Jacobian as in the helix model; there the
slopes are columns of the Jacobian's own forward pass (`jacobian_and_predictions`: on the
bundled example the fit's first call 8.6-8.8 -> 5.2-6.2 s on 2 cores, its later calls
0.14 -> 0.10 s; before, the slopes' own forward pass nested in the fit's had its program
trace ~12 500 operations, half of them derivatives thrown away).  The fit
is then Orear's iteration: least squares with the weights held fixed, solved again with the
weights of its solution until they stop moving (`moving_sigmas`).  One least-squares solve
whose weights moved at every evaluation was not consistent -- the cost it compared moved
with weights its Jacobian held fixed -- and its steps were rejected until its trust region
collapsed: on the bundled example 31 steps, 19 of them rejected or at round-off, stopping
~0.1 standard errors short of the fixed point.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._compile import jit
from .._dna import helix_from_bdna, kT as thermal_energy
from .._misc import host_method, jacobian_forward, random_integers, random_normal, random_split
from .._status import RESULTS
from .._tweezer import PLECTONEME_TWIST_PERSISTENCE, filament_and_rise, response_point
from ._models import AbstractForwardModel, forward_model
from ._parameters import ModelParameter
from ._tweezer_data import TweezerData

#: Typical zero-load moduli of DNA used only for the default start (S pN, C pN nm^2):
#: Bryant et al., Nature 424, 338 (2003).
_START_MODULI = (1100.0, 410.0)


class TweezerModel(AbstractForwardModel):
    """Extensions (and measured torques) of molecules in magnetic or optical tweezers."""

    force: Array
    control: Array  # turns, or a torque where torque_controlled
    torque_controlled: Array
    extension: Array
    extension_sigma: Array
    force_sigma: Array | None
    turns_sigma: Array | None
    torque_points: Array  # indices of the points with a measured torque
    measured_torque: Array
    measured_torque_sigma: Array
    molecule: Array
    n_bp: Array
    kT: Array
    length_per_bp: Array
    molecule_names: tuple[str, ...] = eqx.field(static=True)
    control_kind: str = eqx.field(static=True)  # "free" (zero torque), "torque", "turns" or "mixed"
    fit_offsets: bool = eqx.field(static=True)
    plectonemes_free: bool = eqx.field(static=True)
    errors_in_variables: bool = eqx.field(static=True)
    forward_mode_only: ClassVar[bool] = True
    default_starts: ClassVar[int] = 1

    @property
    def frame_observed(self) -> bool:
        return False

    @property
    def parameters(self) -> tuple[ModelParameter, ...]:
        own = (
            ModelParameter("persistence_length", 50.0, 50.0, True),
            ModelParameter("plectoneme_twist_persistence", PLECTONEME_TWIST_PERSISTENCE, PLECTONEME_TWIST_PERSISTENCE, True, not self.plectonemes_free),
        )
        offsets = tuple(ModelParameter(f"offset_{name}", 0.0, 10.0, False, not self.fit_offsets) for name in self.molecule_names)
        return own + offsets

    def _predict(self, rod, extra, force, control):
        """Extension (nm, with the offsets), torque, phase and ok per point.  Data of one
        `control_kind` pass it to `response_point` as a Python constant (free swivels: one
        solve of the rod per point; turned points: the iteration); mixed data trace it per
        point, one program for all (two specialised ones would compile twice as long and,
        measured, run no faster)."""
        A, P, offsets = extra[0], extra[1], extra[2:]
        _, rise = filament_and_rise(rod, self.length_per_bp)
        N = self.n_bp[self.molecule]
        kind = self.control_kind

        def one(F, x, n, by_torque):
            if kind == "free":
                per_bp, by_torque = 0.0, True
            elif kind == "torque":
                per_bp, by_torque = x, True
            elif kind == "turns":
                per_bp, by_torque = 2 * jnp.pi * x / n, False
            else:
                per_bp = jnp.where(by_torque, x, 2 * jnp.pi * x / n)
            ext, _, torque, phase, _, _, _, result = response_point(
                rod, self.length_per_bp, rise, F, per_bp, by_torque, A, P, self.kT
            )
            return n * ext, torque, phase, result == RESULTS.successful

        extension, torque, phase, ok = jax.vmap(one)(force, control, N, self.torque_controlled)
        return extension + offsets[self.molecule], torque, phase, ok

    def residuals(self, rod, extra):
        if self.errors_in_variables:
            (extension, torque, phase, ok), sigma = self._predict_with_sigma(rod, extra)
        else:
            extension, torque, phase, ok = self._predict(rod, extra, self.force, self.control)
            sigma = self.extension_sigma
        return self._normalised(extension, torque, phase, ok, sigma)

    def _normalised(self, extension, torque, phase, ok, sigma):
        """The residuals of predicted extensions (their sigmas `sigma`) and torques, and the
        predictions."""
        r_extension = (extension - self.extension) / sigma
        r_torque = (torque[self.torque_points] - self.measured_torque) / self.measured_torque_sigma
        predicted = {
            "extension": extension, "torque": torque, "phase": phase, "ok": ok,
            "extension_sigma": sigma,
        }
        if self.errors_in_variables:
            predicted["residual_sigma"] = jnp.concatenate([sigma, self.measured_torque_sigma])
        return jnp.concatenate([r_extension, r_torque]), predicted

    def moving_sigmas(self, predicted):
        return predicted["residual_sigma"] if self.errors_in_variables else None

    def _control_directions(self):
        """The tangents `(k, n)` of the force and of the control along which the controls
        with sigmas (force, turns) vary, and those sigmas `(k, n)`."""
        directions = []
        if self.force_sigma is not None:
            directions.append((jnp.ones_like(self.force), jnp.zeros_like(self.control), self.force_sigma))
        if self.turns_sigma is not None:
            turned = jnp.where(self.torque_controlled, 0.0, 1.0)
            directions.append((jnp.zeros_like(self.force), turned, jnp.where(self.torque_controlled, 0.0, self.turns_sigma)))
        return tuple(jnp.stack(parts) for parts in zip(*directions))

    def _effective_sigma(self, slopes, control_sigma):
        """The extension sigma and the controls' sigmas through the model's `slopes` `(k, n)`
        (its extensions' derivatives along `_control_directions`), in quadrature."""
        return jnp.sqrt(self.extension_sigma**2 + jnp.sum((slopes * control_sigma) ** 2, axis=0))

    def _predict_with_sigma(self, rod, extra):
        """`_predict` at the data, and the effective extension sigma of errors in variables:
        the extension sigma and the force and turns sigmas through the slopes of the model,
        in quadrature, held fixed (no derivative: a weight, not a prediction).  The slopes
        are tangents of the same evaluation (one instance of the model in the program)."""
        d_force, d_control, control_sigma = self._control_directions()

        def along(t_force, t_control):
            return jax.jvp(lambda F, c: self._predict(rod, extra, F, c), (self.force, self.control), (t_force, t_control))

        if d_force.shape[0] == 1:  # no batch of one direction to trace
            predicted, tangents = along(d_force[0], d_control[0])
            slopes = tangents[0][None]
        else:
            predicted, tangents = jax.vmap(along, out_axes=(None, 0))(d_force, d_control)
            slopes = tangents[0]
        return predicted, self._effective_sigma(jax.lax.stop_gradient(slopes), control_sigma)

    def jacobian_and_predictions(self, q, param):
        """With errors in variables, the slopes that weight the residuals are columns of
        the Jacobian: one forward pass in the free values `q` and the controls' directions
        (`_control_directions`) together.  Differentiating `residuals`, whose slopes are a
        forward pass of their own, would nest the two, tracing the derivatives of the slopes
        in the parameters (a third order of the rod's helix, thrown away: the weights are
        held fixed) for nothing."""
        if not self.errors_in_variables:
            return super().jacobian_and_predictions(q, param)
        d_force, d_control, control_sigma = self._control_directions()
        n = q.shape[0]

        def predictions(x):
            q, t = x[:n], x[n:]
            extension, torque, phase, ok = self._predict(
                param.rod(q), param.extra_vector(q), self.force + t @ d_force, self.control + t @ d_control
            )
            return (extension, torque), (extension, torque, phase, ok)

        x = jnp.concatenate([q, jnp.zeros(d_force.shape[0], q.dtype)])
        (d_extension, d_torque), (extension, torque, phase, ok) = jacobian_forward(predictions, x, has_aux=True, through_loops=True)
        sigma = self._effective_sigma(jnp.moveaxis(d_extension[:, n:], -1, 0), control_sigma)
        r, predicted = self._normalised(extension, torque, phase, ok, sigma)
        J = jnp.concatenate([
            d_extension[:, :n] / sigma[:, None],
            d_torque[self.torque_points, :n] / self.measured_torque_sigma[:, None],
        ])
        return J, (r, predicted)

    @host_method
    def isotropic_start(self, uhat):
        """The isotropic rod $\\mathrm{diag}(B, B, C_w)$ with intrinsic helix `uhat` whose
        stretch and twist moduli at zero load are typical of DNA (S = 1100 pN, C = 410 pN
        nm^2): the classical open-coiled spring formulas of `effective_moduli` solved for
        $(B, C_w)$; (1000, 1000) where they give no positive solution."""
        u = np.asarray(uhat, float)
        norm = float(np.linalg.norm(u))
        kappa, tau = float(np.hypot(u[0], u[1])), float(u[2])
        if norm == 0 or kappa == 0 or tau <= 0:
            return 1000.0, 1000.0
        sin, cos, radius = tau / norm, kappa / norm, kappa / norm**2
        S, C = _START_MODULI
        matrix = sin * np.array([[sin**2, cos**2], [cos**2, sin**2]])  # (B, Cw) -> (S r^2, C)
        B, Cw = np.linalg.solve(matrix, np.array([S * radius**2, C]))
        return (float(B), float(Cw)) if B > 0 and Cw > 0 else (1000.0, 1000.0)

    @host_method
    def twist_scale(self, p0):
        norm = float(np.linalg.norm(np.asarray(p0)[5:]))
        return norm if norm > 0 else 1.0 / float(self.length_per_bp)

    def with_data(self, data):
        if not isinstance(data, TweezerData):
            raise ValueError(f"a fit to TweezerData needs TweezerData, got {type(data).__name__}")
        return forward_model(data, fit_offsets=self.fit_offsets, errors_in_variables=self.errors_in_variables)

    def replicates(self, kind, n, key, predicted):
        size = self.force.shape[0]
        per_point = ("force", "control", "torque_controlled", "extension", "extension_sigma", "force_sigma", "turns_sigma", "molecule")
        if kind == "cases":
            if self.torque_points.shape[0]:
                raise ValueError("bootstrap kind='cases' of tweezer data with measured torques is not supported; use 'parametric'")
            idx = random_integers(key, (n, size), 0, size)
            batch = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), self)
            return eqx.tree_at(
                lambda m: [getattr(m, f) for f in per_point if getattr(self, f) is not None],
                batch,
                [getattr(self, f)[idx] for f in per_point if getattr(self, f) is not None],
            )
        batch = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), self)
        ke, kt = random_split(key, 2)
        extension = predicted["extension"][None] + self.extension_sigma[None] * random_normal(ke, (n, size))
        torque = predicted["torque"][self.torque_points][None] + self.measured_torque_sigma[None] * random_normal(
            kt, (n, self.torque_points.shape[0])
        )
        return eqx.tree_at(lambda m: (m.extension, m.measured_torque), batch, (extension, torque))


def _control_kind(torque_controlled, control) -> str:
    if torque_controlled.all():
        return "free" if not np.any(control) else "torque"
    return "turns" if not torque_controlled.any() else "mixed"


@jit(run_once=True)
def _constants(temperature):
    """$k_BT$ at `temperature` (which `TweezerData` has checked) and the B-DNA filament
    length per base pair: one program, not a dozen one-operation programs (each a
    compilation or a cache lookup on a process's first fit)."""
    return thermal_energy(temperature), helix_from_bdna()[2]


@forward_model.register
def _(data: TweezerData, *, fit_offsets=None, errors_in_variables=None, branch=None, use_register=None) -> TweezerModel:
    if branch is not None or use_register is not None:
        raise ValueError("fit_stiffness: branch= and use_register= apply to HelixData only")
    has_control_sigma = data.force_sigma is not None or data.turns_sigma is not None
    if errors_in_variables is None:
        errors_in_variables = has_control_sigma
    elif errors_in_variables and not has_control_sigma:
        raise ValueError("errors_in_variables=True needs force_sigma and/or turns_sigma in the data")
    torque_points = np.flatnonzero(np.asarray(data.has_measured_torque))
    torque_controlled = np.asarray(data.torque_controlled)
    control = np.where(torque_controlled, np.asarray(data.torque), np.asarray(data.turns))
    turned = ~torque_controlled & (np.abs(control) > 0)
    measured = np.zeros(0) if data.measured_torque is None else np.asarray(data.measured_torque)[torque_points]
    measured_sigma = np.zeros(0) if data.measured_torque_sigma is None else np.asarray(data.measured_torque_sigma)[torque_points]
    # Host arrays placed with `device_put`: `jnp.asarray` with a dtype was a small program each.
    dtype = jnp.result_type(float)
    kT, length_per_bp = _constants(data.temperature)
    return TweezerModel(
        force=data.force,
        control=jax.device_put(np.asarray(control, dtype)),
        torque_controlled=jax.device_put(torque_controlled),
        extension=data.extension,
        extension_sigma=data.extension_sigma,
        force_sigma=data.force_sigma if errors_in_variables else None,
        turns_sigma=data.turns_sigma if errors_in_variables else None,
        torque_points=jax.device_put(torque_points.astype(np.int32)),
        measured_torque=jax.device_put(np.asarray(measured, dtype)),
        measured_torque_sigma=jax.device_put(np.asarray(measured_sigma, dtype)),
        molecule=data.molecule,
        n_bp=jnp.asarray(data.n_bp, dtype),
        kT=kT,
        length_per_bp=jnp.asarray(length_per_bp, dtype),
        molecule_names=tuple(data.molecule_names),
        control_kind=_control_kind(torque_controlled, control),
        fit_offsets=bool(fit_offsets),
        plectonemes_free=bool(turned.any()),
        errors_in_variables=bool(errors_in_variables),
    )
