"""The elastic rod: a quadratic strain energy $W = \\tfrac12 (u-\\hat u)^T K (u-\\hat u)$."""

from __future__ import annotations

import contextlib

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._compile import jit
from ._misc import float_dtype, is_concrete


#: The parameters of a `Rod` as a flat vector (`rod_vector`, `rod_from_vector`, the fits).
PARAMETER_NAMES = ("K1", "K2", "K3", "K13", "K23", "uhat1", "uhat2", "uhat3")


def _positive_definite(K1, K2, K3, K13, K23, uhat):
    """Mask of rods whose stiffness is finite and positive definite, and ``uhat`` finite.

    $K$ has a diagonal upper-left 2x2 block, so by the Schur complement it is positive
    definite iff $K_1 > 0$, $K_2 > 0$ and $K_3 - K_{13}^2/K_1 - K_{23}^2/K_2 > 0$.
    """
    xp = np if is_concrete(K1, K2, K3, K13, K23, uhat) else jnp
    if xp is np:  # NumPy's operators: JAX's would compile each operation eagerly (~20 ms each)
        K1, K2, K3, K13, K23, uhat = (np.asarray(a) for a in (K1, K2, K3, K13, K23, uhat))
    finite = (
        xp.isfinite(K1)
        & xp.isfinite(K2)
        & xp.isfinite(K3)
        & xp.isfinite(K13)
        & xp.isfinite(K23)
        & xp.all(xp.isfinite(uhat), axis=-1)
    )
    safe1 = xp.where(K1 > 0, K1, 1.0)
    safe2 = xp.where(K2 > 0, K2, 1.0)
    schur = K3 - K13**2 / safe1 - K23**2 / safe2
    return finite & (K1 > 0) & (K2 > 0) & (schur > 0)


class Rod(eqx.Module):
    """An inextensible, unshearable elastic rod with quadratic strain energy.

    $$W(u) = \\tfrac12 (u - \\hat u)^T K (u - \\hat u), \\qquad m = K(u - \\hat u),$$

    $$K = \\begin{pmatrix} K_1 & 0 & K_{13} \\\\ 0 & K_2 & K_{23} \\\\
    K_{13} & K_{23} & K_3 \\end{pmatrix}.$$

    `K1`, `K2` are the bending stiffnesses about the directors $d_1$, $d_2$ (the
    convention is $K_1 \\le K_2$: $d_1$ is the softer axis), `K3` the torsional stiffness,
    `K13`, `K23` the bend-twist couplings and `uhat` the intrinsic (unstressed) twist
    vector in the director frame.  Units are free but must be consistent: with
    stiffness in [force x length^2], twists in [1/length], moments come out in
    [force x length].

    Every field may carry leading batch dimensions (all of the same shape; `uhat` adds
    a trailing 3), so a batch of rods is itself a `Rod` and can be `jax.vmap`-ed over.

    A non-finite or non-positive-definite stiffness raises `ValueError` when the values
    are concrete, and an `equinox` runtime error (`eqx.error_if`) when they are traced.
    $K_1 > K_2$ is allowed (nothing in helixrod needs the canonical order), and
    `Rod.canonical()` returns the equivalent rod with $K_1 \\le K_2$.

    **Example**

    ```python
    rod = helixrod.Rod(1.0, 1.5, 0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
    rod.energy(jnp.array([0.3, 0.2, 1.5]))
    ```
    """

    K1: Float[Array, "*batch"]
    K2: Float[Array, "*batch"]
    K3: Float[Array, "*batch"]
    K13: Float[Array, "*batch"]
    K23: Float[Array, "*batch"]
    uhat: Float[Array, "*batch 3"]

    def __init__(
        self,
        K1: ArrayLike,
        K2: ArrayLike,
        K3: ArrayLike,
        K13: ArrayLike = 0.0,
        K23: ArrayLike = 0.0,
        uhat: ArrayLike = (0.0, 0.0, 0.0),
    ):
        # Constant inputs (also inside a trace: a rod built from numbers in a jitted function)
        # are checked now, in Python; only traced ones get a runtime check, whose host
        # callback keeps a program out of the persistent compilation cache.
        concrete = is_concrete(K1, K2, K3, K13, K23, uhat)
        with jax.ensure_compile_time_eval() if concrete else contextlib.nullcontext():
            dtype = jnp.result_type(float)
            K1, K2, K3, K13, K23 = (jnp.asarray(k, dtype=dtype) for k in (K1, K2, K3, K13, K23))
            uhat = jnp.asarray(uhat, dtype=dtype)
            if uhat.ndim == 0 or uhat.shape[-1] != 3:
                raise ValueError(f"Rod: uhat must have a trailing axis of length 3, got shape {uhat.shape}")
            shapes = {k.shape for k in (K1, K2, K3, K13, K23)}
            shapes.add(uhat.shape[:-1])
            try:
                batch = jnp.broadcast_shapes(*shapes)
            except ValueError:
                raise ValueError(f"Rod: stiffness and uhat batch shapes do not broadcast: {sorted(shapes)}") from None
            K1, K2, K3, K13, K23 = (jnp.broadcast_to(k, batch) for k in (K1, K2, K3, K13, K23))
            uhat = jnp.broadcast_to(uhat, batch + (3,))
            ok = _positive_definite(K1, K2, K3, K13, K23, uhat)
            message = (
                "Rod: stiffness must be finite and positive definite "
                "(K1 > 0, K2 > 0, K3 - K13**2/K1 - K23**2/K2 > 0) and uhat finite"
            )
            if concrete:
                bad = ~np.asarray(ok)
                if bad.any():
                    where = "" if bad.ndim == 0 else f" (bad entries at batch indices {np.argwhere(bad)[:5].tolist()})"
                    raise ValueError(
                        message
                        + where
                        + f"; got K1={np.asarray(K1)}, K2={np.asarray(K2)}, K3={np.asarray(K3)}, "
                        f"K13={np.asarray(K13)}, K23={np.asarray(K23)}, uhat={np.asarray(uhat)}"
                    )
            else:
                K1 = eqx.error_if(K1, ~ok, message)
        self.K1, self.K2, self.K3, self.K13, self.K23, self.uhat = K1, K2, K3, K13, K23, uhat

    def __repr__(self) -> str:
        leaves = (self.K1, self.K2, self.K3, self.K13, self.K23, self.uhat)
        if not is_concrete(*leaves):
            return eqx.tree_pformat(self)  # traced: shapes and dtypes only
        if self.K1.ndim == 0:
            stiffness = ", ".join(f"{n}={float(v):.6g}" for n, v in zip(("K1", "K2", "K3", "K13", "K23"), leaves))
            uhat = ", ".join(f"{float(x):.6g}" for x in np.asarray(self.uhat))
            return f"Rod({stiffness}, uhat=({uhat}))"
        show = lambda x: np.array2string(np.asarray(x), precision=6, separator=", ", threshold=6, edgeitems=2).replace("\n", "")
        fields = ", ".join(f"{n}={show(v)}" for n, v in zip(("K1", "K2", "K3", "K13", "K23", "uhat"), leaves))
        return f"Rod(batch {tuple(self.K1.shape)}, {fields})"

    # -- constitutive law ---------------------------------------------------------------
    @property
    def K(self) -> Float[Array, "*batch 3 3"]:
        """The stiffness matrix, shape `batch + (3, 3)`."""
        z = jnp.zeros_like(self.K1)
        rows = (
            jnp.stack([self.K1, z, self.K13], axis=-1),
            jnp.stack([z, self.K2, self.K23], axis=-1),
            jnp.stack([self.K13, self.K23, self.K3], axis=-1),
        )
        return jnp.stack(rows, axis=-2)

    def _strain(self, u):
        # Component by component: the rod's batch and `u`'s broadcast without implicit
        # rank promotion (the components of an unbatched rod are scalars).
        u = jnp.asarray(u)
        return tuple(u[..., i] - self.uhat[..., i] for i in range(3))

    def moment(self, u: ArrayLike) -> Float[Array, "... 3"]:
        """Contact moment $m = K(u - \\hat u)$ (local components); `u` has a trailing 3."""
        v1, v2, v3 = self._strain(u)
        return jnp.stack(
            [
                self.K1 * v1 + self.K13 * v3,
                self.K2 * v2 + self.K23 * v3,
                self.K13 * v1 + self.K23 * v2 + self.K3 * v3,
            ],
            axis=-1,
        )

    def energy(self, u: ArrayLike) -> Float[Array, "..."]:
        """Strain energy density $W(u) = \\tfrac12 (u-\\hat u)^T K (u-\\hat u)$."""
        v1, v2, v3 = self._strain(u)
        return 0.5 * (
            self.K1 * v1 * v1 + self.K2 * v2 * v2 + self.K3 * v3 * v3 + 2 * (self.K13 * v1 + self.K23 * v2) * v3
        )

    def twist(self, m: ArrayLike) -> Float[Array, "... 3"]:
        """Inverse constitutive law: the twist vector $u = \\hat u + K^{-1} m$."""
        m = jnp.asarray(m)
        # Block elimination of the diagonal 2x2 block: exact and branch-free.
        schur = self.K3 - self.K13**2 / self.K1 - self.K23**2 / self.K2
        m1, m2, m3 = m[..., 0], m[..., 1], m[..., 2]
        v3 = (m3 - self.K13 * m1 / self.K1 - self.K23 * m2 / self.K2) / schur
        v1 = (m1 - self.K13 * v3) / self.K1
        v2 = (m2 - self.K23 * v3) / self.K2
        return jnp.stack([self.uhat[..., 0] + v1, self.uhat[..., 1] + v2, self.uhat[..., 2] + v3], axis=-1)

    # -- equivalent forms ---------------------------------------------------------------
    def canonical(self) -> "Rod":
        """The same rod with $K_1 \\le K_2$.

        Where $K_1 > K_2$ the frame is turned by $+\\pi/2$ about $d_3$
        ($d_1' = d_2$, $d_2' = -d_1$): $K' $ has $(K_2, K_1, K_3, K_{23}, -K_{13})$,
        $\\hat u' = (\\hat u_2, -\\hat u_1, \\hat u_3)$, and a register $\\varphi$ becomes
        $\\varphi + \\pi/2$.  Rods already canonical are returned unchanged.
        """
        swap = self.K1 > self.K2
        u1, u2, u3 = self.uhat[..., 0], self.uhat[..., 1], self.uhat[..., 2]
        return Rod(
            jnp.where(swap, self.K2, self.K1),
            jnp.where(swap, self.K1, self.K2),
            self.K3,
            jnp.where(swap, self.K23, self.K13),
            jnp.where(swap, -self.K13, self.K23),
            jnp.stack([jnp.where(swap, u2, u1), jnp.where(swap, -u1, u2), u3], axis=-1),
        )

    def dimensionless(self) -> dict[str, Array]:
        """Dimensionless stiffness ratios (reference report, section 1.6).

        Returns `a = K2/K1` (asymmetry), `Gamma = K3/K1` (twist-to-bend ratio),
        `k13 = K13/K1`, `k23 = K23/K1`.  Dividing every moment by $K_1$ (times a length
        scale) leaves a rod with $K_1 = 1$: `rod.scaled(1/rod.K1)`.
        """
        return {
            "a": self.K2 / self.K1,
            "Gamma": self.K3 / self.K1,
            "k13": self.K13 / self.K1,
            "k23": self.K23 / self.K1,
        }

    def scaled(self, factor: ArrayLike) -> "Rod":
        """The rod with every stiffness multiplied by `factor` (wrenches scale alike)."""
        return Rod(
            self.K1 * factor,
            self.K2 * factor,
            self.K3 * factor,
            self.K13 * factor,
            self.K23 * factor,
            self.uhat,
        )

    # -- constructors from material and section data ------------------------------------
    @classmethod
    def from_section(
        cls,
        E: float,
        I1: float,
        I2: float,
        J: float,
        *,
        G: float | None = None,
        nu: float | None = None,
        uhat: ArrayLike = (0.0, 0.0, 0.0),
    ) -> "Rod":
        """Rod of Young's modulus `E` and shear modulus `G` (or Poisson ratio `nu`,
        $G = E / (2(1+\\nu))$), second moments `I1`, `I2` (about $d_1$, $d_2$) and
        torsion constant `J`: $K_1 = E I_1$, $K_2 = E I_2$, $K_3 = G J$ (eq. 19 of the
        reference report)."""
        G = _shear_modulus(E, G, nu)
        return cls(E * I1, E * I2, G * J, uhat=uhat)

    @classmethod
    def circular(
        cls,
        E: float,
        radius: float,
        *,
        G: float | None = None,
        nu: float | None = None,
        uhat: ArrayLike = (0.0, 0.0, 0.0),
    ) -> "Rod":
        """Solid circular wire: $I_1 = I_2 = \\pi r^4/4$, $J = \\pi r^4/2$."""
        inertia = math.pi * radius**4 / 4
        return cls.from_section(E, inertia, inertia, 2 * inertia, G=G, nu=nu, uhat=uhat)

    @classmethod
    def elliptical(
        cls,
        E: float,
        a: float,
        b: float,
        *,
        G: float | None = None,
        nu: float | None = None,
        uhat: ArrayLike = (0.0, 0.0, 0.0),
    ) -> "Rod":
        """Solid elliptical section, semi-axis `a` along $d_1$ and `b` along $d_2$.

        $I_1 = \\pi a b^3/4$, $I_2 = \\pi a^3 b/4$, and Saint-Venant's torsion constant
        $J = \\pi a^3 b^3/(a^2 + b^2)$.  With $a \\ge b$ the rod is canonical ($K_1 \\le K_2$).
        """
        I1 = math.pi * a * b**3 / 4
        I2 = math.pi * a**3 * b / 4
        J = math.pi * a**3 * b**3 / (a**2 + b**2)
        return cls.from_section(E, I1, I2, J, G=G, nu=nu, uhat=uhat)


def _shear_modulus(E, G, nu):
    if (G is None) == (nu is None):
        raise ValueError("give exactly one of G (shear modulus) or nu (Poisson ratio)")
    if G is None:
        if not -1.0 < nu < 0.5:
            raise ValueError(f"Poisson ratio nu must lie in (-1, 1/2), got {nu}")
        return E / (2.0 * (1.0 + nu))
    return G


def section_scales(E: float, I1: float, area: float, density: float = 1.0) -> dict[str, float]:
    """Natural scales of a rod (reference report, section 1.6, eqs. 25-27).

    From Young's modulus `E` (force/area), the second moment `I1` (length^4), the section
    `area` (length^2) and the `density` (mass/volume): length $L = \\sqrt{I_1/A}$, time
    $T = \\sqrt{\\rho I_1 / (A E)}$, force $\\phi = A E$; moments scale as $\\phi L$, twists as
    $1/L$, stiffnesses as $\\phi L^2$.  Returns a dict of Python floats with keys `length`,
    `time`, `force`, `moment`.
    """
    length = math.sqrt(I1 / area)
    return {
        "length": length,
        "time": math.sqrt(density * I1 / (area * E)),
        "force": area * E,
        "moment": area * E * length,
    }


def rod_vector(rod: Rod) -> Float[Array, "*batch 8"]:
    """The parameters of `rod` in `PARAMETER_NAMES` order (K1, K2, K3, K13, K23, uhat)."""
    stiffness = jnp.stack([rod.K1, rod.K2, rod.K3, rod.K13, rod.K23], axis=-1)
    return jnp.concatenate([stiffness, rod.uhat], axis=-1)


def rod_from_vector(p: ArrayLike, *, checked: bool = False) -> Rod:
    """The `Rod` with parameters `p` (`PARAMETER_NAMES` order, shape `(8,)`).  By default
    *without* the constructor's positive-definiteness check: for parameterisations that
    guarantee it, where a check that raises inside an optimiser's trial step (or one member
    of a batch) would abort all of them; `checked=True` runs it (e.g. for values read from
    a file).  A concrete `p` is checked on the host and split into the rod's leaves by one
    compiled call (the constructor's check costs milliseconds of small device operations,
    a transfer of each leaf ~20 us, eager slicing as much)."""
    if is_concrete(p) and np.shape(p) == (8,):
        host = np.asarray(p, float)
        if checked:
            check_rod_vector(host)
        return jax.tree_util.tree_unflatten(_rod_treedef(), _rod_leaves(host.astype(float_dtype())))
    p = jnp.asarray(p, float_dtype())
    if checked:
        return Rod(p[0], p[1], p[2], p[3], p[4], p[5:8])  # raises the constructor's error
    return jax.tree_util.tree_unflatten(_rod_treedef(), [p[0], p[1], p[2], p[3], p[4], p[5:8]])


@jit
def _rod_leaves(p):
    return [p[0], p[1], p[2], p[3], p[4], p[5:8]]


def check_rod_vector(p: ArrayLike) -> None:
    """Raise the `Rod` constructor's `ValueError` unless the concrete parameters `p`
    (`PARAMETER_NAMES` order, shape `(8,)`) are a valid rod; on the host, with no rod built
    (for checks of a start or a value read from a file)."""
    host = np.asarray(p, float)
    if not bool(_positive_definite(*host[:5], host[5:])):
        Rod(*host[:5], host[5:])  # raises the constructor's error, which names the problem


@functools.cache
def _rod_treedef():
    return jax.tree_util.tree_structure(Rod(1.0, 1.0, 1.0))


def check_quadratic_rod(rod, owner: str) -> None:
    """Raise `ValueError` unless `rod` is a `Rod` (the quadratic energy, batched or not):
    the helix solvers find the registers of its energy in closed form; a general law
    (`StrainEnergyRod`) has no such form (it works with `solve_static` and the finite-rod
    solvers)."""
    if not isinstance(rod, Rod):
        hint = " (a StrainEnergyRod works with solve_static and the finite-rod solvers)" if hasattr(rod, "strain_energy") else ""
        raise ValueError(f"{owner}: rod must be a helixrod.Rod, got {type(rod).__name__}{hint}")


def check_one_rod(rod, owner: str) -> None:
    """Raise `ValueError` unless `rod` is a single rod (not a batch), read from the shape of
    its `uhat` (or, for a law without one, of its inverse law; without running it)."""
    uhat = getattr(rod, "uhat", None)
    if uhat is not None:
        shape = jnp.shape(uhat)
    else:
        shape = jax.eval_shape(rod.twist, jax.ShapeDtypeStruct((3,), float_dtype())).shape
    if shape != (3,):
        raise ValueError(f"{owner} takes one rod: jax.vmap over a batch of rods")
