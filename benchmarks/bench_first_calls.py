"""Benchmark: the first call of each main entry point, as a user meets it.

Each case runs in a fresh Python process (imports not counted): the wall and CPU time of
its first call (tracing, lowering, XLA compilation and the run), its peak RSS, then the
time of a second call with new values (the compiled run alone).  Three settings, each in
its own processes:

* `options`: helixrod as shipped (its compiler options, `helixrod._compile`), cold: an
  empty persistent compilation cache;
* `warm`: the same with the cache the cold process filled (a second process);
* `xla-default`: `HELIXROD_COMPILER_OPTIONS=0`, XLA's default CPU emitters, cold;
* `low-opt`: helixrod's options with JAX's `JAX_DISABLE_MOST_OPTIMIZATIONS=1` (LLVM's
  backend at level 0, without its expensive passes; the quick test tier's setting), cold: the
  first call it saves against the later calls it slows.

The targets of issue 20: every first call <= 5 s cold and <= 1.5 s warm on 2 cores;
`jax.grad` through `solve_static` <= 15 s and <= 1 GB.

Program sizes (`--sizes`): each case once more in a fresh process with an empty cache, with
XLA dumping every program it compiles (``--xla_dump_to``): the number of programs, their
HLO instructions as JAX hands them to XLA (before XLA's passes) and as XLA compiles them
(after), in total and for the largest program.  `--source PATH` measures another source tree
of helixrod (e.g. a `git worktree` of an older commit) under `--label`, so that sizes before
and after a change sit side by side; the dump's own cost makes these runs' times meaningless.

Usage: python benchmarks/bench_first_calls.py [--quick] [--cases a,b] [--one-core]
       python benchmarks/bench_first_calls.py --sizes [--cases a,b] [--source PATH --label NAME]
Writes benchmarks/results/bench_first_calls.json (bench_program_sizes.json with --sizes); the
cases not run keep their earlier results there (those of a run on the same machine with the
same --one-core setting; sizes: of the same label).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from _machine import cpu_model

#: The helices of the fit cases: 60 of a coupled rod, and `helix_data(seed)` their forces and
#: moments with 1 % noise.
HELIX_DATA = """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
rng = np.random.default_rng(0)
kappa, tau = rng.uniform(0.3, 2.0, 60), rng.uniform(-1.5, 1.5, 60)
eq = hr.helix_equilibria(rod, kappa, tau)
force, moment = np.asarray(eq.force[:, 0]), np.asarray(eq.moment[:, 0])
def helix_data(seed):
    noise = np.random.default_rng(seed).normal(size=(2, 60))
    return hr.HelixData(force + 0.01 * noise[0], moment + 0.01 * noise[1], kappa, tau, force_sigma=0.01, moment_sigma=0.01)
"""

CASES = {
    "helix_equilibria": """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
k = np.random.default_rng(0).uniform(0, 3, 10_000)
t = np.random.default_rng(1).uniform(-3, 3, 10_000)
call = lambda i: hr.helix_equilibria(rod, k + 0.01 * i, t)
""",
    "solve_static": """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
call = lambda i: hr.solve_static(rod, jnp.array([0.1, -0.2, 0.5 + 0.01 * i]), jnp.array([0.3, 0.2, 0.9]), 40.0)
""",
    "solve_static (201 saved points)": """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
s = np.linspace(0.0, 40.0, 201)
call = lambda i: hr.solve_static(rod, jnp.array([0.1, -0.2, 0.5 + 0.01 * i]), jnp.array([0.3, 0.2, 0.9]), 40.0, saveat=s,
                                 outputs=("wrench", "frame", "centreline")).x
""",
    "jax.grad(solve_static)": """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
end_moment = lambda n0: jnp.sum(hr.solve_static(rod, n0, jnp.array([0.3, 0.2, 0.9]), 40.0).m[-1] ** 2)
call = lambda i: jax.grad(end_moment)(jnp.array([0.1, -0.2, 0.5 + 0.01 * i]))
""",
    "helices_under_load": """
rod = hr.Rod(1.0, 1.5, 0.8, 0.5, 0.5, (1.0, 0.0, 0.0))
call = lambda i: hr.helices_under_load(rod, -0.49 + 0.01 * i, 0.81, kappa_max=3.0, tau_range=(-3.0, 3.0))
""",
    "fit_stiffness": HELIX_DATA + """
def call(i):
    return hr.fit_stiffness(helix_data(i), uhat=(1.0, 0.0, 0.0)).rod
""",
    "bootstrap": HELIX_DATA + """
data = helix_data(0)
fit = hr.fit_stiffness(data, uhat=(1.0, 0.0, 0.0))
call = lambda i: hr.bootstrap(data, fit, 100, jax.random.key(i)).samples["K1"]
""",
    "fit_stiffness (shape data)": """
truth = hr.Rod(1.0, 1.4, 0.8, K13=0.15, K23=-0.1, uhat=(0.3, 0.9, 0.35))
s = jnp.linspace(0.0, 6.0, 25)
ends = [hr.Loaded((0.02, 0.0, 0.05), (0.0, 0.03, 0.0)), hr.Loaded((-0.03, 0.02, 0.0), (0.02, 0.0, -0.02))]
data = hr.synthetic_shape_data(truth, 6.0, s, ends, 2e-3, jax.random.key(3))
init = hr.Rod(1.3, 1.3, 1.0, uhat=truth.uhat)
call = lambda i: hr.fit_stiffness(data, uhat=truth.uhat, init=eqx.tree_at(lambda r: r.K1, init, 1.3 + 0.01 * i), rtol=1e-8, atol=1e-10).cost
""",
    "solve_boundary_value": """
rod = hr.Rod(1.0, 1.5, 0.8)
call = lambda i: hr.solve_boundary_value(rod, 1.0, end=hr.Loaded(force=(0.0, 0.0, -3.0 - 0.1 * i)))
""",
    "force_extension (50 points)": """
spring = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
call = lambda i: hr.force_extension(spring, 30.0, np.linspace(0.0, 0.05 + 0.001 * i, 50), rotation=30.0 * 1.044).extension
""",
    "force_extension (across its critical force)": """
spring = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
length = 3 * 2 * np.pi / np.hypot(1.0, 0.3)
call = lambda i: hr.force_extension(spring, length, np.linspace(0.01, 0.5 + 0.001 * i, 50)).critical
""",
    "stability_atlas (20 x 20)": """
spring = hr.Rod(1.0, 1.0, 1 / 1.3, uhat=(0.0, 1.0, 0.3))
kappa, tau = np.meshgrid(np.linspace(0.2, 1.5, 20), np.linspace(-1.0, 1.0, 20))
call = lambda i: hr.stability_atlas(spring, kappa + 0.01 * i, tau, 5.0).critical_length
""",
    "follow_branch (Euler column)": """
rod = hr.Rod(1.0, 2.0, 0.8)
load = lambda P: hr.Loaded(force=jnp.stack([0.0 * P, 0.0 * P, -P]))
call = lambda i: hr.follow_branch(rod, 1.0, load, (1.0, 12.0 + 0.1 * i)).parameter
""",
    "fit_stiffness (tweezer example)": """
rod = hr.dna.load_tweezer_example().rod
data = hr.dna.load_tweezer_curves_example().data
fix = {"K1": float(rod.K1), "K13": 0.0}
call = lambda i: hr.fit_stiffness(data, uhat=rod.uhat, init=rod, fix=fix, fit_offsets=True).rod
""",
}

RUNNER = """
import json, resource, sys, time
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import helixrod as hr
if sys.argv[1]:
    hr.enable_compilation_cache(sys.argv[1])
{setup}
def timed(i):
    wall, cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(call(i))
    return time.perf_counter() - wall, time.process_time() - cpu
first_wall, first_cpu = timed(0)
later_wall, _ = timed(1)
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
print(json.dumps(dict(first_wall_s=first_wall, first_cpu_s=first_cpu, later_wall_s=later_wall, peak_rss_gb=rss)))
"""


def run_case(name: str, cache: str, default_xla: bool, one_core: bool, low_opt: bool = False, env_extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env["HELIXROD_COMPILER_OPTIONS"] = "0" if default_xla else "1"
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1" if low_opt else "0"
    env.update(env_extra or {})
    command = [sys.executable, "-c", RUNNER.format(setup=CASES[name]), cache]
    if one_core:
        command = ["taskset", "-c", "1"] + command
        env["NUMBA_NUM_THREADS"] = "1"  # the register kernel's threads, on the one core
    out = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{name} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


#: An HLO instruction in XLA's text dump: an indented `name = type op(...)` line.
_INSTRUCTION = re.compile(r"^\s+(?:ROOT\s+)?\S+ = \S", re.M)


def hlo_instructions(path: Path) -> int:
    """The number of HLO instructions in one module of XLA's text dump."""
    return len(_INSTRUCTION.findall(path.read_text(errors="replace")))


def program_sizes(name: str, source: str | None) -> dict:
    """The programs the first call of case `name` compiles (cold, fresh process), from XLA's
    dump: how many, their HLO instructions before and after XLA's passes, and the largest."""
    with tempfile.TemporaryDirectory() as dump, tempfile.TemporaryDirectory() as cache:
        flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump} --xla_dump_hlo_as_text".strip()
        extra = {"XLA_FLAGS": flags}
        if source:
            extra["PYTHONPATH"] = os.pathsep.join(filter(None, [source, os.environ.get("PYTHONPATH")]))
        run_case(name, cache, False, False, env_extra=extra)
        programs = []
        for before in sorted(Path(dump).glob("*.before_optimizations.txt")):
            module = before.name[: -len(".before_optimizations.txt")]
            after = next(iter(Path(dump).glob(f"{module}.*after_optimizations.txt")), None)
            programs.append(dict(name=module.split(".", 1)[-1], hlo_ops=hlo_instructions(before),
                                 hlo_ops_optimized=hlo_instructions(after) if after else None))
    largest = max(programs, key=lambda p: p["hlo_ops"])
    return dict(programs=len(programs), hlo_ops=sum(p["hlo_ops"] for p in programs),
                hlo_ops_optimized=sum(p["hlo_ops_optimized"] or 0 for p in programs), largest=largest)


def _commit(source: str | None) -> str:
    """The commit of the source tree measured (short hash and date), or "unknown"."""
    where = Path(source).resolve() if source else Path(__file__).resolve().parent
    out = subprocess.run(["git", "-C", str(where), "log", "-1", "--format=%h %cs"], capture_output=True, text=True, check=False)
    return out.stdout.strip() or "unknown"


def main_sizes(names: list[str], source: str | None, label: str) -> None:
    out = Path(__file__).parent / "results" / "bench_program_sizes.json"
    try:
        labels = json.loads(out.read_text())["labels"]
    except (OSError, ValueError, KeyError):
        labels = {}
    entry = labels.get(label, {})
    commit = _commit(source)
    cases = entry.get("cases", {}) if entry.get("commit") == commit else {}
    print(f"{label} ({commit}): {'case':34s} {'programs':>8s} {'HLO in':>8s} {'HLO out':>8s}  largest (in / out)")
    for name in names:
        r = program_sizes(name, source)
        cases[name] = r
        big = r["largest"]
        print(f"  {name:40s} {r['programs']:8d} {r['hlo_ops']:8d} {r['hlo_ops_optimized']:8d}  "
              f"{big['name']} ({big['hlo_ops']} / {big['hlo_ops_optimized']})", flush=True)
    labels[label] = dict(commit=commit, cases=cases)
    out.write_text(json.dumps(dict(labels=labels), indent=1))
    print(f"wrote {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--quick", action="store_true", help="the three shortest cases")
    parser.add_argument("--one-core", action="store_true", help="pin each process to one core (taskset -c 1)")
    parser.add_argument("--sizes", action="store_true", help="program sizes from XLA's dump instead of times")
    parser.add_argument("--source", default=None, help="with --sizes: the helixrod source tree (its src/) to measure")
    parser.add_argument("--label", default="current", help="with --sizes: the name the sizes are stored under")
    args = parser.parse_args()
    if args.sizes:
        main_sizes(args.cases.split(","), args.source, args.label)
        return
    out = Path(__file__).parent / "results" / "bench_first_calls.json"
    machine = f"{os.cpu_count()} cores ({cpu_model()})"
    # Cases not run now keep their earlier results, from a run on this machine with the same --one-core.
    try:
        earlier = json.loads(out.read_text())
        same = earlier.get("one_core") == args.one_core and earlier.get("machine") == machine
        results = earlier["results"] if same else {}
    except (OSError, ValueError, KeyError):
        results = {}
    print(f"{'case':22s} {'setting':12s} {'first (wall)':>12s} {'first (CPU)':>12s} {'later':>10s} {'peak RSS':>9s}")
    names = ["helix_equilibria", "solve_static", "helices_under_load"] if args.quick else args.cases.split(",")
    for name in names:
        results[name] = {}
        with tempfile.TemporaryDirectory() as cache:
            for setting, cache_dir, default_xla, low_opt in (
                ("options", cache, False, False), ("warm", cache, False, False), ("xla-default", "", True, False),
                ("low-opt", "", False, True),
            ):
                r = run_case(name, cache_dir, default_xla, args.one_core, low_opt)
                results[name][setting] = r
                print(
                    f"{name:22s} {setting:12s} {r['first_wall_s']:11.2f}s {r['first_cpu_s']:11.2f}s "
                    f"{1e3 * r['later_wall_s']:8.1f}ms {r['peak_rss_gb']:8.2f}G",
                    flush=True,
                )
    out.write_text(json.dumps(dict(one_core=args.one_core, machine=machine, results=results), indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
