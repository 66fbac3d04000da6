"""A general convex constitutive law: any strain energy $W(u - \\hat u)$ given as a JAX function."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float


class StrainEnergyRod(eqx.Module):
    """A rod with a general convex strain energy $W(v)$, $v = u - \\hat u$ (reference report,
    section 1.6.2).  Usable wherever `solve_static` and `first_integrals` take a `Rod`, and
    by the finite-rod solvers (`solve_boundary_value`, the response curves, `bulk_helix`);
    not by the helix solvers (`helix_equilibria`, sweeps, fits, `stability_atlas`), which
    find the registers of the quadratic energy in closed form (they raise `ValueError`).
    The energy and the Newton settings are static: a program compiled for one energy is
    compiled again for another function (even one with the same body).

    `strain_energy(v)` maps a `(3,)` array to a scalar; it must be smooth and strictly
    convex with its minimum at $v = 0$.  The moment is $m = \\nabla W(u - \\hat u)$ (by
    autodiff) and the inverse law $u(m)$ solves $\\nabla W(v) = m$ by Newton's method
    (`optimistix.root_find`, differentiated implicitly), started from the linearised law
    $v_0 = (\\nabla^2 W(0))^{-1} m$.  Leading batch dimensions are handled by
    `jnp.vectorize`.

    **Example**

    ```python
    W = lambda v: 0.5 * (v[0]**2 + 1.5 * v[1]**2 + 0.8 * v[2]**2) + 0.1 * v[0]**4
    rod = helixrod.StrainEnergyRod(W, uhat=(1.0, 0.0, 0.0))
    n0, m0 = jnp.array([0.0, 0.0, 0.1]), jnp.array([0.2, 0.0, 0.3])   # start wrench
    sol = helixrod.solve_static(rod, n0, m0, 10.0)
    ```

    `rtol`, `atol`: the tolerances of the Newton solve of the inverse law.
    """

    # Static (part of the rod's structure, not a leaf): a program compiled for the rod
    # (`jax.jit` takes array leaves only) is compiled for this energy and these settings.
    strain_energy: Callable[[Array], Array] = eqx.field(static=True)
    uhat: Float[Array, "3"]
    newton: optx.Newton = eqx.field(static=True)

    def __init__(self, strain_energy: Callable, uhat: ArrayLike = (0.0, 0.0, 0.0), *, rtol=1e-13, atol=1e-13):
        uhat = jnp.asarray(uhat, jnp.result_type(float))
        if uhat.shape != (3,):
            raise ValueError(f"StrainEnergyRod: uhat must have shape (3,), got {uhat.shape}")
        self.strain_energy = strain_energy
        self.uhat = uhat
        self.newton = optx.Newton(rtol=rtol, atol=atol)

    def energy(self, u: ArrayLike) -> Array:
        """$W(u - \\hat u)$; `u` has a trailing 3."""
        return jnp.vectorize(lambda ui: self.strain_energy(ui - self.uhat), signature="(3)->()")(jnp.asarray(u))

    def moment(self, u: ArrayLike) -> Array:
        """$m = \\nabla W(u - \\hat u)$."""
        return jnp.vectorize(lambda ui: jax.grad(self.strain_energy)(ui - self.uhat), signature="(3)->(3)")(
            jnp.asarray(u)
        )

    def twist(self, m: ArrayLike) -> Array:
        """Inverse law: $u$ with $\\nabla W(u - \\hat u) = m$ (Newton, implicit derivatives)."""
        gradient = jax.grad(self.strain_energy)

        def one(mi):
            hessian0 = jax.hessian(self.strain_energy)(jnp.zeros_like(mi))
            v0 = jnp.linalg.solve(hessian0, mi)
            sol = optx.root_find(lambda v, target: gradient(v) - target, self.newton, v0, mi, throw=False)
            # Flag a failed Newton solve with NaN rather than a silent wrong twist.
            return jnp.where(sol.result == optx.RESULTS.successful, sol.value + self.uhat, jnp.nan)

        return jnp.vectorize(one, signature="(3)->(3)")(jnp.asarray(m))
