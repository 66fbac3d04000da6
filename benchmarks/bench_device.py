"""helix_equilibria and sweep on whatever device JAX picks (a GPU when there is one),
unchanged code: throughput against the numpy peer on the host CPU, and agreement with the
same computation on JAX's CPU backend; `solve_static` and `jax.grad` through it at the
defaults (one solve and a vmapped batch) against the CPU backend.

    python benchmarks/bench_device.py [--quick]

Writes benchmarks/results/bench_device_<platform>.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import helixrod as hr  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _numpy_peer import numpy_helix_equilibria  # noqa: E402
from _timing import best_time  # noqa: E402

RESULTS = Path(__file__).parent / "results"
ROD_ARGS = dict(K1=1.0, K2=1.5, K3=0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))
ROD = hr.Rod(**ROD_ARGS)


def fields(kappa, tau):
    eq = hr.helix_equilibria(ROD, kappa, tau)
    return eq.phi, eq.valid, eq.force, eq.moment, eq.stable


def end_moment(n0, m0):
    """A scalar of the non-helical solve of bench_kirchhoff, shortened to L = 10: at L = 40
    its gradients reach 1e4-1e8 (the flow amplifies perturbations), so two correct backends
    (or a loop and a vmap on one) differ there by up to ~1e-5 relative; at L = 10 by ~1e-10."""
    return jnp.sum(hr.solve_static(ROD, n0, m0, 10.0).m[-1] ** 2)


def kirchhoff_on_device(quick: bool) -> dict:
    """One solve and its gradient (the forward sensitivities), then a batch of them under
    vmap, on the default device and on the CPU backend: agreement, compile and run times."""
    rng = np.random.default_rng(2)
    batch = 1000 if quick else 10_000
    n0 = np.array([0.1, -0.2, 0.5]) + 0.05 * rng.normal(size=(batch, 3))
    m0 = np.array([0.3, 0.2, 0.9]) + 0.05 * rng.normal(size=(batch, 3))
    value_and_grad = jax.jit(jax.value_and_grad(end_moment, argnums=(0, 1)))
    batched = jax.jit(jax.vmap(jax.value_and_grad(end_moment, argnums=(0, 1))))
    out = {}
    for name, device in (("device", jax.devices()[0]), ("cpu", jax.devices("cpu")[0])):
        with jax.default_device(device):
            one = jax.device_put((n0[0], m0[0]), device)
            many = jax.device_put((n0, m0), device)
            start = time.perf_counter()
            first = jax.block_until_ready(value_and_grad(*one))
            compile_one = time.perf_counter() - start
            seconds_one = best_time(lambda: value_and_grad(*one), 5)
            start = time.perf_counter()
            values = jax.block_until_ready(batched(*many))
            compile_many = time.perf_counter() - start
            seconds_many = best_time(lambda: batched(*many), 2)
        out[name] = dict(first_call_s=compile_one, seconds=seconds_one, batch=batch, batch_first_call_s=compile_many,
                         batch_seconds=seconds_many, solves_per_s=batch / seconds_many,
                         value=np.asarray(first[0]).item(), grad=np.concatenate([np.asarray(g) for g in first[1]]).tolist(),
                         batch_values=np.asarray(values[0]), batch_grads=np.concatenate([np.asarray(g) for g in values[1]], axis=1))
        print(f"solve_static + grad on {name}: one {seconds_one * 1e3:.2f} ms (first call {compile_one:.1f} s); "
              f"vmap of {batch}: {seconds_many * 1e3:.1f} ms ({batch / seconds_many:.3g} solves/s, first call {compile_many:.1f} s)")
    here, cpu = out["device"], out["cpu"]
    scale = np.max(np.abs(cpu["batch_grads"]), axis=1)
    agreement = dict(
        value_rel=abs(here["value"] - cpu["value"]) / abs(cpu["value"]),
        grad_rel=float(np.max(np.abs(np.subtract(here["grad"], cpu["grad"]))) / np.max(np.abs(cpu["grad"]))),
        batch_value_rel=float(np.max(np.abs(here["batch_values"] - cpu["batch_values"]) / np.abs(cpu["batch_values"]))),
        batch_grad_rel=float(np.max(np.max(np.abs(here["batch_grads"] - cpu["batch_grads"]), axis=1) / scale)),
        batch_finite=bool(np.all(np.isfinite(here["batch_grads"]))))
    print("solve_static on the device against the CPU backend: " + ", ".join(f"{k} {v:.1e}" if isinstance(v, float) else f"{k} {v}"
                                                                     for k, v in agreement.items()))
    for side in (here, cpu):
        del side["batch_values"], side["batch_grads"]
    return dict(device=here, cpu=cpu, agreement=agreement)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    opts = parser.parse_args()
    device = jax.devices()[0]
    report = dict(device=str(device), platform=device.platform, device_kind=getattr(device, "device_kind", ""),
                  host=platform.processor() or platform.machine(), jax=jax.__version__, runs=[], sweeps=[])
    print(f"device: {device} ({report['device_kind']})")

    # Agreement with the CPU backend (same program, other compiler).
    rng = np.random.default_rng(0)
    k, t = rng.uniform(0.01, 3.0, 100_000), rng.uniform(-3.0, 3.0, 100_000)
    here = [np.asarray(x) for x in jax.jit(fields)(jnp.asarray(k), jnp.asarray(t))]
    cpu = jax.devices("cpu")[0]
    with jax.default_device(cpu):
        there = [np.asarray(x) for x in jax.jit(fields)(jnp.asarray(k), jnp.asarray(t))]
    same_valid = bool(np.array_equal(here[1], there[1]))
    v = here[1]
    dphi = float(np.max(np.abs(np.angle(np.exp(1j * (here[0][v] - there[0][v]))))))
    dforce = float(np.max(np.abs(here[2][v] - there[2][v]) / np.maximum(1, np.abs(there[2][v]))))
    report["agreement_with_cpu"] = dict(points=k.size, same_valid=same_valid, max_dphi=dphi, max_rel_dforce=dforce,
                                        same_stable=bool(np.array_equal(here[4], there[4])))
    print(f"against the CPU backend on {k.size} helices: same registers {same_valid}, max |dphi| {dphi:.1e}, "
          f"max rel dF {dforce:.1e}")

    sizes = [10**5, 10**6, 10**7] if opts.quick else [10**5, 10**6, 10**7, 3 * 10**7]
    jitted = jax.jit(fields)
    for n in sizes:
        k, t = rng.uniform(0.01, 3.0, n), rng.uniform(-3.0, 3.0, n)
        kj, tj = jax.device_put(k), jax.device_put(t)
        start = time.perf_counter()
        compiled = jitted.lower(kj, tj).compile()
        compile_s = time.perf_counter() - start
        jax.block_until_ready(compiled(kj, tj))
        seconds = best_time(lambda: compiled(kj, tj), 3)
        peer = None
        if n <= 10**6:
            peer = best_time(lambda: numpy_helix_equilibria(**ROD_ARGS, kappa=k, tau=t), 1)
        report["runs"].append(dict(points=n, seconds=seconds, compile_s=compile_s, points_per_s=n / seconds,
                                   numpy_host_seconds=peer))
        print(f"helix_equilibria {n:>10} helices: {seconds * 1e3:9.2f} ms ({n / seconds:.3g}/s), compile {compile_s:.1f} s"
              + ("" if peer is None else f"; numpy on the host {peer:.2f} s ({peer / seconds:.0f}x)"))

    grids = [(1000, ("count",)), (3163, ("count",)), (3163, ("force", "moment", "stable", "count"))]
    if not opts.quick:
        grids.append((10_000, ("count",)))
    for n_side, names in grids:
        kappa, tau = np.linspace(0.01, 3.0, n_side), np.linspace(-3.0, 3.0, n_side)
        hr.sweep(ROD, kappa[:2], tau[:2], fields=names, progress=False)  # compile
        seconds = best_time(lambda: hr.sweep(ROD, kappa, tau, fields=names, progress=False), 2)
        report["sweeps"].append(dict(points=n_side**2, fields=list(names), seconds=seconds, points_per_s=n_side**2 / seconds))
        print(f"sweep {n_side**2:>10} points {names}: {seconds:.2f} s ({n_side**2 / seconds:.3g}/s)")
    report["kirchhoff"] = kirchhoff_on_device(opts.quick)
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"bench_device_{device.platform}.json"
    path.write_text(json.dumps(report, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
