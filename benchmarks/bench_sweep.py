"""Speed of the kappa-tau atlas: `helixrod.sweep` against the numpy peer
(`_numpy_peer.numpy_helix_equilibria`: batched companion eigenvalues + Newton polish +
wrench + stability) in the same process; compile time apart; peak memory of a
count-only sweep in a fresh subprocess; achieved flop rate against a rough machine peak
(flops per point from XLA's cost analysis of the compiled chunk).

    python benchmarks/bench_sweep.py --quick     # 1e5 ... 2e6 points
    python benchmarks/bench_sweep.py             # 1e5 ... 1e8 points

Writes benchmarks/results/bench_sweep.json and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
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

ROD_ARGS = dict(K1=1.0, K2=1.5, K3=0.8, K13=0.5, K23=0.5, uhat=(1.0, 0.0, 0.0))  # Chouaieb-Goriely-Maddocks fig. 2
ROD = hr.Rod(ROD_ARGS["K1"], ROD_ARGS["K2"], ROD_ARGS["K3"], ROD_ARGS["K13"], ROD_ARGS["K23"], ROD_ARGS["uhat"])
FIELD_SETS = {
    "count": ("count",),
    "wrench": ("force", "moment", "stable", "count"),
    "all": hr.SweepResult.FIELDS,
}
RESULTS = Path(__file__).parent / "results"


def grid(n_points):
    side = int(round(np.sqrt(n_points)))
    return np.linspace(0.01, 3.0, side), np.linspace(-3.0, 3.0, int(round(n_points / side)))


def flops_per_point(fields):
    """XLA cost-analysis flops (and transcendentals) per point of the program a sweep chunk
    runs: `helix_equilibria` and the requested fields on one cache-sized batch of 32 768
    points, which `helix_equilibria` runs in one pass (XLA's cost analysis would count the
    body of its chunk loop only once on larger batches).  XLA counts every branch of the
    register solver's robust fallback (taken by a few points per chunk at most), so this
    overstates the work done on the usual path."""
    n = 32_768
    kappa = jnp.linspace(0.01, 3.0, n)
    tau = jnp.linspace(-3.0, 3.0, n)

    def chunk(kappa, tau):
        # The fields as `sweep` derives them from `helix_equilibria`.
        eq = hr.helix_equilibria(ROD, kappa, tau)
        out = {name: getattr(eq, name) for name in fields if name in hr.SweepResult.REGISTER_FIELDS}
        out["count"] = jnp.sum(eq.valid, axis=-1, dtype=jnp.int8)
        out["stable_count"] = jnp.sum(eq.stable, axis=-1, dtype=jnp.int8)
        out["continuum"], out["straight"] = eq.continuum, eq.straight
        best = jnp.argmin(jnp.where(eq.stable, eq.energy, jnp.inf), axis=-1)[..., None]
        for name in ("phi", "force", "moment"):
            out["stable_" + name] = jnp.take_along_axis(getattr(eq, name), best, axis=-1)[..., 0]
        return {name: out[name] for name in fields}

    cost = _cost(jax.jit(chunk), kappa, tau)
    return cost["flops"] / n, cost.get("transcendentals", float("nan")) / n


def _cost(fn, *args):
    cost = fn.lower(*args).compile().cost_analysis()
    return cost[0] if isinstance(cost, list) else cost


def machine_peak_flops():
    """Rough float64 peak: cores x clock x SIMD lanes x 2 (FMA) x 2 (FMA ports)."""
    cores = os.cpu_count() or 1
    mhz, lanes = 2000.0, 2
    try:
        info = Path("/proc/cpuinfo").read_text()
        mhz = float(next(line.split(":")[1] for line in info.splitlines() if line.startswith("cpu MHz")))
        lanes = 8 if " avx512f" in info else 4 if " avx2" in info else 2
    except (OSError, StopIteration, ValueError):
        pass
    return cores * mhz * 1e6 * lanes * 2 * 2, dict(cores=cores, mhz=mhz, f64_lanes=lanes)


def memory_probe(n_points, fields):
    """Peak RSS of a fresh process running one sweep (run as a subprocess).

    The peak is the kernel's high-water mark of the child's own address space (VmHWM);
    `getrusage(...).ru_maxrss` would not do: Linux carries it over fork + exec, so a child
    of a big parent reports the parent's size."""
    code = (
        "import resource, time, jax, numpy as np, json, sys\n"
        "def hwm():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmHWM:'): return int(line.split()[1])\n"
        "    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "sys.path.insert(0, %r)\n"
        "import helixrod as hr\nfrom bench_sweep import ROD, grid\n"
        "base = hwm()\n"
        "k, t = grid(%d)\nstart = time.perf_counter()\n"
        "r = hr.sweep(ROD, k, t, fields=%r, progress=False)\n"
        "print(json.dumps({'seconds': time.perf_counter() - start, 'points': k.size * t.size,"
        " 'baseline_mb': base / 1024, 'peak_mb': hwm() / 1024}))\n"
    ) % (str(Path(__file__).parent), n_points, tuple(fields))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(hr.__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def peer_accuracy(n_points=20_000, seed=0):
    rng = np.random.default_rng(seed)
    k, t = rng.uniform(0.01, 3.0, n_points), rng.uniform(-3.0, 3.0, n_points)
    peer = numpy_helix_equilibria(**{**ROD_ARGS}, kappa=k, tau=t)
    eq = jax.jit(hr.helix_equilibria)(ROD, k, t)
    same_valid = np.all(np.asarray(eq.valid) == peer["valid"], axis=1)
    v = peer["valid"] & same_valid[:, None]
    dphi = np.abs(np.angle(np.exp(1j * (np.asarray(eq.phi)[v] - peer["phi"][v]))))
    rel_force = np.abs(np.asarray(eq.force)[v] - peer["force"][v]) / np.maximum(1, np.abs(peer["force"][v]))
    same_stable = np.array_equal(np.asarray(eq.stable)[v], peer["stable"][v])
    return dict(points=n_points, count_agreement=float(same_valid.mean()), max_dphi=float(dphi.max()),
                max_rel_force=float(rel_force.max()), stable_agrees=bool(same_stable))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1e5 ... 2e6 points")
    opts = parser.parse_args()
    sizes = [100_000, 500_000, 2_000_000] if opts.quick else [100_000, 1_000_000, 10_000_000, 100_000_000]
    peer_sizes = [s for s in sizes if s <= 2_000_000]
    repeats = 2 if opts.quick else 3
    peak, machine = machine_peak_flops()
    report = dict(machine=dict(machine, platform=platform.platform(), devices=[str(d) for d in jax.local_devices()],
                               peak_gflops_estimate=peak / 1e9, note="shared 2-core CPU: timings noisy, pessimistic"),
                  rod=ROD_ARGS, runs=[], peer=[], compile_s={}, flops_per_point={})
    print(f"machine: {machine}, rough f64 peak {peak / 1e9:.1f} GFLOP/s")
    report["peer_accuracy"] = acc = peer_accuracy()
    print(f"numpy peer vs helix_equilibria on {acc['points']} random points: count agrees {acc['count_agreement']:.5f}, "
          f"max |dphi| {acc['max_dphi']:.2e}, max rel dF {acc['max_rel_force']:.2e}, stable agrees {acc['stable_agrees']}")
    for name, fields in FIELD_SETS.items():
        k, t = grid(65536)
        start = time.perf_counter()
        hr.sweep(ROD, k, t, fields=fields, progress=False)  # compile + one chunk
        report["compile_s"][name] = time.perf_counter() - start
        flops, tpp = flops_per_point(fields)
        report["flops_per_point"][name] = dict(flops=flops, transcendentals=tpp)
        print(f"[{name}] compile+first chunk {report['compile_s'][name]:.1f} s; XLA cost analysis per point: "
              f"{flops:.0f} flops (counting every fallback branch) + {tpp:.0f} transcendentals")
    print(f"{'fields':>8} {'points':>11} {'time s':>9} {'points/s':>11} {'GFLOP/s':>8} {'% peak':>7} {'vs numpy':>9}")
    peer_rate = {}
    for n in peer_sizes:
        k, t = grid(n)
        K, T = np.meshgrid(k, t, indexing="ij")
        seconds = best_time(lambda: numpy_helix_equilibria(**ROD_ARGS, kappa=K.ravel(), tau=T.ravel()), 1)
        peer_rate[n] = K.size / seconds
        report["peer"].append(dict(points=K.size, seconds=seconds, points_per_s=peer_rate[n]))
        print(f"{'numpy':>8} {K.size:>11} {seconds:>9.3f} {peer_rate[n]:>11.3g}")
    for name, fields in FIELD_SETS.items():
        for n in sizes:
            if n >= 10_000_000 and name != "count":
                continue  # outputs alone would be GBs; count-only streams
            k, t = grid(n)
            seconds = best_time(lambda: hr.sweep(ROD, k, t, fields=fields, progress=False), 1 if n >= 10_000_000 else repeats)
            rate = k.size * t.size / seconds
            gflops = rate * report["flops_per_point"][name]["flops"] / 1e9
            ratio = rate / peer_rate[n] if n in peer_rate else None
            report["runs"].append(dict(fields=name, points=k.size * t.size, seconds=seconds, points_per_s=rate,
                                       gflops=gflops, fraction_of_peak=gflops * 1e9 / peak, speedup_vs_numpy=ratio))
            print(f"{name:>8} {k.size * t.size:>11} {seconds:>9.3f} {rate:>11.3g} {gflops:>8.2f} {100 * gflops * 1e9 / peak:>6.2f}%"
                  f" {'' if ratio is None else f'{ratio:>8.1f}x'}")
    n_mem = 10_000_000
    report["memory"] = mem = memory_probe(n_mem, ("count",))
    print(f"count-only sweep of {mem['points']} points in a fresh process: peak RSS {mem['peak_mb']:.0f} MB "
          f"(after imports {mem['baseline_mb']:.0f} MB), {mem['seconds']:.1f} s incl. compile")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_sweep.json").write_text(json.dumps(report, indent=2))
    plot(report, RESULTS / "bench_sweep.png")
    print(f"wrote {RESULTS / 'bench_sweep.json'} and .png")


def plot(report, path):
    from matplotlib.figure import Figure

    from helixrod.plot import OKABE_ITO

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for i, name in enumerate(FIELD_SETS):
        runs = [r for r in report["runs"] if r["fields"] == name]
        ax.loglog([r["points"] for r in runs], [r["points_per_s"] for r in runs], "o-", color=OKABE_ITO[i],
                  label=f"helixrod.sweep ({name})")
    peer = report["peer"]
    ax.loglog([r["points"] for r in peer], [r["points_per_s"] for r in peer], "s--", color=OKABE_ITO[7],
              label="numpy peer (eigvals + Newton + wrench)")
    ax.set_xlabel("grid points")
    ax.set_ylabel("points per second")
    ax.set_title("kappa-tau sweep throughput (float64, CPU)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=150)


if __name__ == "__main__":
    main()
