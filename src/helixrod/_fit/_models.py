"""Forward models of `fit_stiffness`: from a rod to the normalised residuals of one kind of
data and the predictions of what was observed.

A model holds its data (arrays, traced) and its configuration (static fields), so one
compilation serves every data set of the same shapes and every refit.  `forward_model(data,
**options)` finds the model of a data type; a new kind of data adds one model class,
registered with `@forward_model.register`, and nothing else.

- `HelixModel` (`HelixData`): for each measured helix $(\\kappa_i, \\tau_i)$ `helix_equilibria`
  gives every register and its axial force and moment $(F_{ij}, M_{ij})$; one register per
  point is chosen (`branch`) and the residuals are $((F_{ij} - F_i)/\\sigma_{F,i},
  (M_{ij} - M_i)/\\sigma_{M,i})$.  The choice is locally constant, and the register itself
  is differentiated by the implicit function theorem (the custom JVP of `register_roots`),
  so the residual is smooth wherever the chosen register is simple.
- `EndResponseModel` (`EndResponseData`): each point is one boundary-value solve of the rod
  at the data's two controls (`axial_response`, independent points from the bulk-helix
  guess); residuals are the two measured responses minus the predictions, over sigma.
- `ShapeModel` (`ShapeData`): one solve per image, saved at the sampled arc lengths;
  residuals are the centreline coordinates minus the points, over sigma.

Derivatives of the finite-rod models are forward mode throughout (one tangent per free
parameter through the implicit function theorem of the shooting root and through the
flows, diffrax `ForwardMode`), so they take least-squares solvers only.  No frame symmetry
applies to them: the clamp fixes the director frame in the lab.  A clamped-clamped shape
without a measured load does not fix the scale of $K$ (scaling $K$ scales the wrench, not
the shape): the identifiability report then shows that null direction.
"""

from __future__ import annotations

import abc
import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._bvp import AXIAL_CONTROLS, AXIAL_OBSERVABLES, BoundaryValueOptions, Clamped, EndCondition
from .._bvp import axial_response, solve_boundary_value
from .._compile import jit
from .._equilibria import helix_equilibria
from .._misc import host_method, jacobian_forward, random_integers, random_normal, random_split
from ._finite_data import EndResponseData, ShapeData
from ._helix_data import HelixData, measured
from ._parameters import ModelParameter

BRANCHES = ("nearest", "stable", "min-energy")


class AbstractForwardModel(eqx.Module):
    """A rod -> residuals map of one kind of data, with what the fit needs to start it."""

    #: Whether the model's derivatives are forward mode only (least-squares solvers only).
    forward_mode_only: ClassVar[bool]
    #: Default number of starts of `fit_stiffness`.
    default_starts: ClassVar[int]
    #: Whether `fit_stiffness` scans the scale of the default first start
    #: (`START_SCAN_FACTORS`) when no `init` is given: for a rough `isotropic_start`.
    scan_start: ClassVar[bool] = False

    @abc.abstractmethod
    def residuals(self, rod, extra: Array) -> tuple[Array, dict[str, Array]]:
        """The normalised residuals `(m,)` of `rod` with the model's own parameters `extra`
        (in the order of `parameters`), and the predictions of the observed quantities by
        name (traced; `jit`, `vmap` and `jacfwd` safe)."""

    @property
    def parameters(self) -> tuple[ModelParameter, ...]:
        """The model's own parameters besides the rod's (none by default)."""
        return ()

    @host_method
    def observed_residuals(self) -> np.ndarray | None:
        """Mask `(m,)` of the residuals that are observations (concrete, from the data), or
        `None` when all are.  A residual of a quantity not measured at a point is held at
        zero, so batches of models (bootstrap replicates) keep one shape; the fit leaves
        it out of its residuals, degrees of freedom and error analysis."""
        return None

    @host_method
    def observation_count(self) -> int | None:
        """The number of observations (residuals the fit keeps), where known without
        evaluating the model (`None` otherwise): the early stop of the default multistart
        checks a best cost against it."""
        return None

    def jacobian_and_predictions(self, q: Array, param) -> tuple[Array, tuple[Array, dict[str, Array]]]:
        """`(J, (r, predicted))`: the Jacobian of the residuals in the free physical values
        `q` of the parameterisation `param`, with any moving sigmas (`moving_sigmas`) held
        fixed, and the residuals and predictions there.  By default forward mode through
        `residuals` (`jacobian_forward`); a model whose sigmas are derivatives of its own
        predictions may take them in the same forward pass."""

        def residuals(qq):
            r, predicted = self.residuals(param.rod(qq), param.extra_vector(qq))
            return r, (r, predicted)

        return jacobian_forward(residuals, q, has_aux=True, through_loops=self.forward_mode_only)

    def moving_sigmas(self, predicted: dict[str, Array]) -> Array | None:
        """The sigmas `(m,)` that divide the residuals, from `residuals`' predictions, where
        they move with the parameters and the Jacobian holds them fixed (errors in
        variables: an effective variance from the model's slopes); `None` (default) where
        no sigma moves.  A stepwise fit (`_stepwise.py`) then holds them fixed across its
        steps and solves again with the sigmas of its solution until they stop moving."""
        return None

    @property
    def holds_weights(self) -> bool:
        """Whether the residuals' weights move with the parameters and `with_weights_held`
        holds them (errors in variables of a model solved in one compiled program)."""
        return False

    def with_weights_held(self, predicted: dict[str, Array]) -> "AbstractForwardModel":
        """The model with its moving weights held at those of `predicted` (the predictions
        of `residuals` at a point): its Jacobian and its cost then agree, and a fit solves
        again with the weights of its solution until they stop moving (Orear's iteration,
        `fit_stiffness`).  Only where `holds_weights`."""
        raise NotImplementedError(f"{type(self).__name__} holds no weights")

    @property
    @abc.abstractmethod
    def frame_observed(self) -> bool:
        """Whether the data fix the director frame (then no frame symmetry applies)."""

    @host_method
    @abc.abstractmethod
    def isotropic_start(self, uhat) -> tuple[float, float]:
        """Bending and twisting stiffness $(B, C)$ of an isotropic rod with intrinsic twist
        `uhat` that roughly fits the data: the default first start."""

    @host_method
    @abc.abstractmethod
    def twist_scale(self, p0) -> float:
        """The unit in which the fit measures twists (`uhat`), from the start vector `p0`."""

    @abc.abstractmethod
    def with_data(self, data) -> "AbstractForwardModel":
        """The model of the same kind and configuration for other data."""

    @abc.abstractmethod
    def replicates(self, kind: str, n: int, key, predicted: dict[str, Array]) -> "AbstractForwardModel":
        """`n` bootstrap replicates of the data, stacked on a leading axis: resampled
        points (`kind="cases"`) or observations redrawn around `predicted` with the data's
        sigmas (`"parametric"`)."""


@functools.singledispatch
def forward_model(data, **options) -> AbstractForwardModel:
    """The forward model of `data` with the model `options` (`None` values take the
    model's defaults); `ValueError` for data of no registered type."""
    types = [t.__name__ for t in forward_model.registry if t is not object]
    names = ", ".join(types[:-1]) + f" or {types[-1]}"
    raise ValueError(f"data must be a {names}, got {type(data).__name__}")


def _only_defaults(data, options):
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise ValueError(f"fit_stiffness: {given[0]}= does not apply to {type(data).__name__}")


# -- helices ----------------------------------------------------------------------------------


class HelixModel(AbstractForwardModel):
    """Axial force and moment (and the register, if fitted) of measured uniform helices."""

    force: Array
    moment: Array
    kappa: Array
    tau: Array
    force_sigma: Array
    moment_sigma: Array
    force_observed: Array  # masks; an unobserved value is 0 with sigma 1 and its residual 0
    moment_observed: Array
    observed_register: Array | None  # (`register` would shadow ABCMeta.register)
    register_sigma: Array | None
    kappa_sigma: Array | None
    tau_sigma: Array | None
    kappa_tau_correlation: Array | None
    branch: str = eqx.field(static=True)
    use_register: bool = eqx.field(static=True)
    errors_in_variables: bool = eqx.field(static=True)
    # Errors in variables: the effective covariance (var F, cov FM, var M) `(n, 3)` of each
    # point's chosen register, held fixed (`with_weights_held`); `None`: moving with K.
    held_covariance: Array | None = None
    forward_mode_only: ClassVar[bool] = False
    default_starts: ClassVar[int] = 32

    @property
    def frame_observed(self) -> bool:
        return self.use_register

    @property
    def holds_weights(self) -> bool:
        return self.errors_in_variables

    def with_weights_held(self, predicted):
        if not self.errors_in_variables:
            raise NotImplementedError("a HelixModel holds weights with errors in variables only")
        return eqx.tree_at(
            lambda m: m.held_covariance, self, predicted["residual_covariance"], is_leaf=lambda x: x is None
        )

    def residuals(self, rod, extra):
        # Only the fields used: over a large data set the other fields' values (and their
        # linearisation in the solver) would be computed and kept for nothing.
        fields = ("force", "moment", "phi", "stable")
        moving = self.errors_in_variables and self.held_covariance is None
        if moving:
            eq, slopes = self._equilibria_with_slopes(rod, fields)
        else:
            eq = helix_equilibria(rod, self.kappa, self.tau, fields=fields)
        sF, sM = self.force_sigma[:, None], self.moment_sigma[:, None]
        errF = eq.force - self.force[:, None]
        errM = eq.moment - self.moment[:, None]
        if self.errors_in_variables:
            if moving:
                covariance = self._effective_covariance(slopes, sF, sM)
            else:
                covariance = tuple(jnp.broadcast_to(c[:, None], errF.shape) for c in self.held_covariance.T)
            rF, rM = _whitened(covariance, errF, errM, sM)
        else:
            rF, rM = errF / sF, errM / sM
        rF = jnp.where(self.force_observed[:, None], rF, 0.0)
        rM = jnp.where(self.moment_observed[:, None], rM, 0.0)
        residuals = [rF, rM]
        if self.use_register:
            dphi = jnp.remainder(eq.phi - self.observed_register[:, None] + jnp.pi, 2 * jnp.pi) - jnp.pi
            if self.register_sigma is not None:
                rphi = dphi / self.register_sigma[:, None]
                residuals.append(rphi)
                distance = rF**2 + rM**2 + rphi**2
            else:
                distance = dphi**2
        else:
            distance = rF**2 + rM**2
        distance = jax.lax.stop_gradient(jnp.where(eq.valid, distance, jnp.inf))
        if self.branch == "min-energy":
            slot = jnp.zeros(self.kappa.shape, jnp.int32)
        else:
            if self.branch == "stable":
                stable = jnp.where(eq.stable, distance, jnp.inf)
                # No stable register (a continuum is neutral): fall back to all valid ones.
                distance = jnp.where(jnp.any(eq.stable, axis=-1, keepdims=True), stable, distance)
            slot = jnp.argmin(distance, axis=-1)
        take = lambda x: jnp.take_along_axis(x, slot[:, None], axis=1)[:, 0]  # noqa: E731
        predicted = {"force": take(eq.force), "moment": take(eq.moment), "register": take(eq.phi), "slot": slot,
                     "stable": take(eq.stable)}
        if self.errors_in_variables:
            predicted["residual_covariance"] = jnp.stack([take(c) for c in covariance], axis=-1)
        return jnp.concatenate([take(r) for r in residuals]), predicted

    def _equilibria_with_slopes(self, rod, fields):
        """`helix_equilibria` at the data and the slopes of its force and moment along kappa
        and tau (dF/dk, dM/dk, dF/dt, dM/dt), held fixed (no gradient: weights): one
        linearisation of the same evaluation, applied to both directions, not a second
        evaluation of the solver for the slopes."""
        eq, linear = jax.linearize(lambda k, t: helix_equilibria(rod, k, t, fields=fields), self.kappa, self.tau)
        ones, zeros = jnp.ones_like(self.kappa), jnp.zeros_like(self.kappa)
        along_k, along_t = linear(ones, zeros), linear(zeros, ones)
        return eq, jax.lax.stop_gradient((along_k.force, along_k.moment, along_t.force, along_t.moment))

    def _effective_covariance(self, slopes, sF, sM):
        """The effective covariance (var F, cov FM, var M) at each register: first-order
        propagation of the errors of kappa and tau (with their correlation) into the 2x2
        covariance of the model's (F, M), added to that of the observed (F, M) (Orear, Am.
        J. Phys. 50 (1982) 912, in two dimensions).  The slopes carry no gradient: as in the
        effective-variance method, the weights are held fixed in the Jacobian, and the fit
        iterates them to their fixed point (`with_weights_held`)."""
        dF_dk, dM_dk, dF_dt, dM_dt = slopes
        ks, ts = self.kappa_sigma[:, None], self.tau_sigma[:, None]
        ckt = self.kappa_tau_correlation[:, None] * ks * ts

        def propagated(a_k, a_t, b_k, b_t):
            return a_k * b_k * ks * ks + (a_k * b_t + a_t * b_k) * ckt + a_t * b_t * ts * ts

        cFF = sF**2 + propagated(dF_dk, dF_dt, dF_dk, dF_dt)
        cMM = sM**2 + propagated(dM_dk, dM_dt, dM_dk, dM_dt)
        both = (self.force_observed & self.moment_observed)[:, None]  # else the one observed alone
        cFM = jnp.where(both, propagated(dF_dk, dF_dt, dM_dk, dM_dt), 0.0)
        return cFF, cFM, cMM

    @host_method
    def isotropic_start(self, uhat):
        """Weighted linear least squares for an isotropic rod (K1 = K2 = B, K3 = C, no
        coupling) with intrinsic twist `uhat`.  Its energy-minimising register puts the
        bending of the helix along the intrinsic one, $(\\sin\\varphi, \\cos\\varphi) \\parallel
        (\\hat u_1, \\hat u_2)$; with $\\rho = |(\\hat u_1, \\hat u_2)|$ there
        $F = |u|\\,(C(\\tau - \\hat u_3) - B\\tau(\\kappa - \\rho)/\\kappa)$ and
        $M = (B(\\kappa - \\rho)\\kappa + C(\\tau - \\hat u_3)\\tau)/|u|$ (Love's formulas for
        $\\rho = 0$), linear in B and C."""
        u1, u2, u3 = (float(x) for x in uhat)
        rho = float(np.hypot(u1, u2))
        k, t = np.asarray(self.kappa), np.asarray(self.tau)
        norm = np.hypot(k, t)
        bend = (k - rho) / k
        # An unobserved value has weight zero: its row drops out.
        sF = np.where(np.asarray(self.force_observed), np.asarray(self.force_sigma), np.inf)
        sM = np.where(np.asarray(self.moment_observed), np.asarray(self.moment_sigma), np.inf)
        A = np.concatenate([
            np.stack([-norm * t * bend, norm * (t - u3)], 1) / sF[:, None],
            np.stack([k * k * bend / norm, (t - u3) * t / norm], 1) / sM[:, None],
        ])
        b = np.concatenate([np.asarray(self.force) / sF, np.asarray(self.moment) / sM])
        x, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
        if rank < 2:  # partial data (force only, uhat3 = 0: only C - B is seen)
            x = _positive_on_line(x, np.linalg.svd(A)[2][-1])
        B, C = x
        # A crude floor: the data may favour a negative value of a poorly seen stiffness.
        floor = max(abs(B), abs(C), 1e-300) * 1e-2
        return max(B, floor), max(C, floor)

    @host_method
    def _observation_masks(self) -> list[np.ndarray]:
        masks = [np.asarray(self.force_observed), np.asarray(self.moment_observed)]
        if self.use_register and self.register_sigma is not None:
            masks.append(np.ones(self.kappa.shape, bool))
        return masks

    @host_method
    def observed_residuals(self):
        masks = self._observation_masks()
        return None if all(m.all() for m in masks) else np.concatenate(masks)

    @host_method
    def observation_count(self):
        return int(sum(m.sum() for m in self._observation_masks()))

    @host_method
    def twist_scale(self, p0):
        return float(np.median(np.hypot(np.asarray(self.kappa), np.asarray(self.tau))))

    def with_data(self, data):
        if not isinstance(data, HelixData):
            raise ValueError(f"a fit to HelixData needs HelixData, got {type(data).__name__}")
        return forward_model(
            data, branch=self.branch, use_register=self.use_register, errors_in_variables=self.errors_in_variables
        )

    def replicates(self, kind, n, key, predicted):
        size = self.kappa.shape[0]
        if kind == "cases":  # every array of the model is per point
            idx = random_integers(key, (n, size), 0, size)
            return jax.tree.map(lambda a: a[idx], self)
        batch = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), self)
        kf, km = random_split(key, 2)
        zF, zM = random_normal(kf, (n, size)), random_normal(km, (n, size))
        if self.errors_in_variables:
            # With the errors of kappa and tau propagated: the effective covariance's
            # Cholesky factor, as the residuals are whitened by it.
            covariance = tuple(predicted["residual_covariance"][None, :, i] for i in range(3))
            l11, l21, l22 = _cholesky_2x2(covariance, 0.0)
            dF, dM = l11 * zF, l21 * zF + l22 * zM
        else:
            dF, dM = self.force_sigma[None] * zF, self.moment_sigma[None] * zM
        force = predicted["force"][None] + dF
        moment = predicted["moment"][None] + dM
        return eqx.tree_at(lambda m: (m.force, m.moment), batch, (force, moment))


def _cholesky_2x2(covariance, floor):
    """The lower Cholesky factor (l11, l21, l22) of the 2x2 `covariance` (var F, cov FM,
    var M), each entry an array; the conditional variance of M at least `floor`."""
    cFF, cFM, cMM = covariance
    l11 = jnp.sqrt(cFF)
    l21 = cFM / l11
    return l11, l21, jnp.sqrt(jnp.maximum(cMM - l21 * l21, floor))


def _whitened(covariance, errF, errM, sM):
    """The residual pair (errF, errM) whitened by the Cholesky factor of its 2x2
    `covariance` (var F, cov FM, var M); `sM` floors the conditional variance of M."""
    l11, l21, l22 = _cholesky_2x2(covariance, sM**2 * 1e-12)
    rF = errF / l11
    return rF, (errM - l21 * rF) / l22


def _positive_on_line(x, v):
    """A point of the line $x + t v$ of equally good solutions with both components
    positive and of the size of the data's scale $|x|$: the middle of the positive segment
    where it is bounded, else where the smaller component equals $|x|$."""
    scale = float(np.linalg.norm(x)) or 1.0
    if np.all(v == 0):
        return np.abs(x) + scale
    lower = [(-xi / vi) for xi, vi in zip(x, v) if vi > 0]  # x_i + t v_i > 0
    upper = [(-xi / vi) for xi, vi in zip(x, v) if vi < 0]
    if lower and upper:
        lo, hi = max(lower), min(upper)
        if lo < hi:
            return x + 0.5 * (lo + hi) * v
        return np.abs(x) + scale
    v = v if lower else -v  # both components grow with t
    t = max((scale - xi) / vi for xi, vi in zip(x, v) if vi > 0)
    return x + t * v


@forward_model.register
def _(data: HelixData, *, branch=None, use_register=None, errors_in_variables=None, **others) -> HelixModel:
    if others:
        raise ValueError(f"fit_stiffness: {next(iter(others))}= does not apply to HelixData")
    fo, mo, force, moment, force_sigma, moment_sigma = _observations(data.force, data.moment, data.force_sigma, data.moment_sigma)
    if branch is None:
        # With one observable per point, "nearest" would match each point to whichever
        # register fits it, which can make an undetermined stiffness look determined.
        complete = bool(np.all(np.asarray(fo)) and np.all(np.asarray(mo)))
        branch = "nearest" if complete else "stable"
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
    if use_register is None:
        use_register = data.register_sigma is not None
    if use_register and data.register is None:
        raise ValueError("use_register=True but the data have no register column")
    has_sigmas = data.kappa_sigma is not None or data.tau_sigma is not None
    errors_in_variables = has_sigmas if errors_in_variables is None else bool(errors_in_variables)
    if errors_in_variables and not has_sigmas:
        raise ValueError("errors_in_variables=True needs kappa_sigma and/or tau_sigma in the data")
    either = lambda x: jnp.zeros_like(data.kappa) if x is None else x  # noqa: E731
    return HelixModel(
        force=force,
        moment=moment,
        kappa=data.kappa,
        tau=data.tau,
        force_sigma=force_sigma,
        moment_sigma=moment_sigma,
        force_observed=fo,
        moment_observed=mo,
        observed_register=data.register if use_register else None,
        register_sigma=data.register_sigma if use_register else None,
        kappa_sigma=either(data.kappa_sigma) if errors_in_variables else None,
        tau_sigma=either(data.tau_sigma) if errors_in_variables else None,
        kappa_tau_correlation=either(data.kappa_tau_correlation) if errors_in_variables else None,
        branch=branch,
        use_register=bool(use_register),
        errors_in_variables=errors_in_variables,
    )


@jit
def _observations(force, moment, force_sigma, moment_sigma):
    """The masks of the measured forces and moments (`HelixData.force_observed`,
    `moment_observed`) and the values and sigmas with neutral entries (0 and 1) where a
    value is missing, in one compiled call (eagerly, some twenty small operations)."""
    fo, mo = measured(force), measured(moment)
    return fo, mo, jnp.where(fo, force, 0.0), jnp.where(mo, moment, 0.0), jnp.where(fo, force_sigma, 1.0), jnp.where(mo, moment_sigma, 1.0)


# -- finite rods ------------------------------------------------------------------------------


class EndResponseModel(AbstractForwardModel):
    """The two measured end responses of a finite rod at its two controls."""

    length: Array
    values: Array  # (n, 4): force, moment, extension, rotation (controls and observations)
    sigma: Array  # (n, 2): of the responses
    controls: str = eqx.field(static=True)
    segments: int = eqx.field(static=True)
    forward_mode_only: ClassVar[bool] = True
    default_starts: ClassVar[int] = 1

    @property
    def frame_observed(self) -> bool:
        return True

    def residuals(self, rod, extra):
        test = AXIAL_CONTROLS[self.controls]
        given = {AXIAL_OBSERVABLES[i]: self.values[:, i] for i in test.controls}
        curve = axial_response(
            rod, self.length, **given, mode="independent", rotation_hint=self.values[:, 3], bulk=False,
            options=BoundaryValueOptions(segments=self.segments, stability_pieces=0), progress=False,
        )
        predicted = {AXIAL_OBSERVABLES[i]: getattr(curve, AXIAL_OBSERVABLES[i]) for i in test.responses}
        prediction = jnp.stack(list(predicted.values()), -1)
        observed = self.values[:, list(test.responses)]
        return ((prediction - observed) / self.sigma).T.reshape(-1), predicted

    @host_method
    def isotropic_start(self, uhat):
        """$K = \\mathrm{diag}(B, B, C)$ from the bulk-helix equations at each point (end
        effects neglected): with $|u| = \\Theta/L$, $u_3 = h\\Theta/L^2$, the multipliers
        $\\mu_2 = F/|u|$, $\\mu_1 = (M - \\mu_2 u_3/|u|)/|u|$ and the register aligned with
        $\\hat u$, $B(\\kappa - \\hat\\kappa) = \\mu_1\\kappa$ and $C(u_3 - \\hat u_3) = \\mu_1 u_3 + \\mu_2$:
        linear least squares for $B$ and $C$; (1, 1) where that is ill-posed."""
        L = float(self.length)
        F, M, h, theta = np.asarray(self.values).T
        norm = theta / L
        u3 = h * theta / L**2
        kappa = np.sqrt(np.maximum(norm**2 - u3**2, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            mu2 = F / norm
            mu1 = (M - mu2 * u3 / norm) / norm
        kappa_hat = float(np.hypot(uhat[0], uhat[1]))
        out = []
        for a, b in ((kappa - kappa_hat, mu1 * kappa), (u3 - uhat[2], mu1 * u3 + mu2)):
            good = np.isfinite(a) & np.isfinite(b)
            denom = float(np.sum(a[good] ** 2))
            if not good.any() or denom <= 0:
                return 1.0, 1.0
            out.append(float(np.sum(a[good] * b[good]) / denom))
        B, C = out
        if not (np.isfinite(B) and np.isfinite(C)) or B <= 0 or C <= 0:
            return 1.0, 1.0
        return B, C

    @host_method
    def twist_scale(self, p0):
        return _twist_scale(p0, self.length)

    def with_data(self, data):
        return forward_model(data)

    def replicates(self, kind, n, key, predicted):
        raise ValueError("bootstrap supports fits to HelixData only (finite-rod fits: resample and refit)")


@forward_model.register
def _(data: EndResponseData, **options) -> EndResponseModel:
    _only_defaults(data, options)
    return EndResponseModel(data.length, data.values, data.sigma, data.controls, data.segments)


class ShapeModel(AbstractForwardModel):
    """Centreline points of a finite rod under known end conditions, one solve per image."""

    length: Array
    s: Array
    points: Array  # (m, p, 3)
    sigma: Array  # (m, p)
    start: Clamped
    end: EndCondition  # stacked over the m images
    segments: int = eqx.field(static=True)
    forward_mode_only: ClassVar[bool] = True
    default_starts: ClassVar[int] = 1
    scan_start: ClassVar[bool] = True

    @property
    def frame_observed(self) -> bool:
        return True

    def residuals(self, rod, extra):
        options = BoundaryValueOptions(segments=self.segments, stability_pieces=0)  # shapes only

        def one(end):
            sol = solve_boundary_value(
                rod, self.length, start=self.start, end=end, saveat=self.s, options=options, throw=False
            )
            return jnp.where(sol.ok, sol.x, jnp.nan)

        # One image after another: under vmap the root finder's choice between a fresh and
        # a secant Jacobian becomes a select that integrates the Jacobian at every step
        # (the README's two-image Jacobian: 0.17-0.34 s with lax.map, 0.49-0.87 s vmapped).
        prediction = jax.lax.map(one, self.end)
        return ((prediction - self.points) / self.sigma[..., None]).reshape(-1), {"points": prediction}

    @host_method
    def isotropic_start(self, uhat):
        """$B = C$ = a stiffness that bends the rod by about a radian under the end loads:
        $|M|L + |F|L^2/2$ (1 when no load is prescribed)."""
        L = float(self.length)
        force = np.max(np.linalg.norm(np.asarray(self.end.force), axis=-1))
        moment = np.max(np.linalg.norm(np.asarray(self.end.moment), axis=-1))
        scale = moment * L + 0.5 * force * L**2
        scale = float(scale) if scale > 0 and np.isfinite(scale) else 1.0
        return scale, scale

    @host_method
    def twist_scale(self, p0):
        return _twist_scale(p0, self.length)

    def with_data(self, data):
        return forward_model(data)

    def replicates(self, kind, n, key, predicted):
        raise ValueError("bootstrap supports fits to HelixData only (finite-rod fits: resample and refit)")


def _twist_scale(p0, length):
    u_norm = float(np.linalg.norm(np.asarray(p0)[5:]))
    return u_norm if u_norm > 0 else 1.0 / float(length)


@forward_model.register
def _(data: ShapeData, **options) -> ShapeModel:
    _only_defaults(data, options)
    return ShapeModel(data.length, data.s, data.points, data.sigma, data.start, data.end, data.segments)
