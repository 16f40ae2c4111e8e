"""Backward Euler against BDF2 (the quasi-Newton solver's two time schemes): order of
accuracy, and what each does to motion its steps do not resolve.

Two experiments on a soft slab (60 x 30 x 8 mm, 6 x 3 x 1 cells, Neo-Hookean, 1000 kg/m^3,
clamped at x = 0), each against the explicit solver at 0.05 of its critical step (an
independent integrator, first order in its tiny step):

* **order**: the slab (E = 30 kPa, damping 1/s) held bent (free end 1 mm up) and released
  under gravity; the largest vertex error after 0.2 s at steps of 20, 10, 5 and 2.5 ms.
  Halving the step divides a first-order scheme's error by 2, a second-order one's by 4.
* **under-resolved motion**: the slab (E = 3 kPa, damping 20/s), its free end held and
  pulled 0.5 mm per 0.05 s step, sagging under gravity from flat: the held end's vertical
  reaction per 0.05 s env step, each scheme with 1 and with 8 sub-steps. The slab's
  first sag oscillation lasts about three 0.05 s steps.
* **robustness on the env scenes**: both envs' default physics under each scheme, 16
  scenes stepped together, the same seeded stream of actions for both (every third step
  extreme: each command at +-1; the others uniform in [-1, 1]): how many env steps were
  unconverged, diverged, re-taken in shorter steps, or non-finite.

Writes docs/benchmarks/time_schemes.{json,md} and docs/img/time_schemes.png.

    python benchmarks/accuracy/time_schemes.py
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from heml_gym.benchmarks.common import parse_arguments, IMAGES, RESULTS, machine_info, markdown_table, write_json

import heml_gym as hg
from heml_gym import materials as M

SCHEMES = ("backward_euler", "bdf2")
MESH = hg.box_mesh((0.06, 0.03, 0.008), (6, 3, 1))
FIXED = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.0))
FREE_END = np.flatnonzero(np.isclose(MESH.vertices[:, 0], 0.06))
GRAVITY = (0.0, 0.0, -9.81)


def released(kind: str, h: float, duration: float = 0.2) -> np.ndarray:
    """Vertex positions (m) of the released slab after ``duration`` s in steps of ``h``."""
    m = hg.Model(MESH, M.NeoHookean(E=30e3, nu=0.4), density=1000.0, gravity=GRAVITY, fixed=FIXED, damping=1.0)
    state, control = m.state(), m.control()
    state.x[0, :, 2] += 0.001 * (MESH.vertices[:, 0] / 0.06) ** 2
    if kind == "explicit":
        solver = hg.ExplicitSolver(m, safety=0.05)
        for _ in range(round(duration / h)):
            solver.step(state, state, control, h, substeps=solver.substeps(h, m.critical_dt()))
    else:
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-10, max_iter=2000, scheme=kind)
        for _ in range(round(duration / h)):
            if not solver.step(state, state, control, h).converged.all():
                raise RuntimeError(f"{kind} at h = {h} s did not converge")
    return state.x[0].copy()


def pulled(kind: str, substeps: int, steps: int = 12, dt: float = 0.05) -> list[float]:
    """The held end's vertical reaction (N) per env step of ``dt`` s, the end pulled along
    x by 0.5 mm per step (for 10 steps, then held)."""
    m = hg.Model(MESH, M.NeoHookean(E=3e3, nu=0.4), density=1000.0, gravity=GRAVITY, fixed=FIXED, damping=20.0)
    state, control = m.state(), m.control()
    control.attach(0, FREE_END, state.x[0])
    if kind == "explicit":
        solver = hg.ExplicitSolver(m, safety=0.05)
    else:
        solver = hg.QuasiNewtonSolver(m, newton_tol=1e-8, max_iter=500, scheme=kind)
    series = []
    for k in range(1, steps + 1):
        control.drive(0, FREE_END, MESH.vertices[FREE_END] + [0.0005 * min(k, 10), 0.0, 0.0])
        n = solver.substeps(dt, m.critical_dt()) if kind == "explicit" else substeps
        stats = solver.step(state, state, control, dt, substeps=n)
        series.append(float(stats.reaction[0, FREE_END, 2].sum()))
    return series


def soak(env_id: str, scheme: str, vector_steps: int, num_envs: int = 16) -> dict:
    """Counts of troubled env steps of ``env_id`` under ``scheme`` (see the docstring)."""
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401

    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        physics={"scheme": scheme})
    obs, _ = venv.reset(seed=7)
    rng = np.random.default_rng(7)
    counts = dict(env_steps=0, unconverged=0, diverged=0, refined=0, non_finite=0, episodes=0)
    for k in range(vector_steps):
        a = rng.uniform(-1.0, 1.0, (num_envs, 4))
        if k % 3 == 0:
            a = np.sign(a)
        obs, reward, terminated, truncated, info = venv.step(a.astype(np.float32))
        counts["env_steps"] += num_envs
        counts["unconverged"] += int((~info["solver_converged"]).sum())
        counts["diverged"] += int(info["simulation_diverged"].sum())
        counts["refined"] += int((info["substep_refinement"] > 1).sum())
        counts["non_finite"] += int((~np.isfinite(obs)).any(axis=1).sum() + (~np.isfinite(reward)).sum())
        counts["episodes"] += int((terminated | truncated).sum())
    venv.close()
    return counts


def main() -> int:
    start = time.perf_counter()
    steps = (0.02, 0.01, 0.005, 0.0025)
    reference = released("explicit", 0.0025)
    order = {kind: [float(np.abs(released(kind, h) - reference).max()) for h in steps] for kind in SCHEMES}
    reaction = {"explicit": pulled("explicit", 0)}
    for kind in SCHEMES:
        for sub in (1, 8):
            reaction[f"{kind}, {sub} sub-step{'s' if sub > 1 else ''}"] = pulled(kind, sub)
    ref = np.array(reaction["explicit"])
    peak = float(np.abs(ref).max())
    deviation = {k: float(np.abs(np.array(v) - ref).max() / peak) for k, v in reaction.items() if k != "explicit"}
    robustness = {env_id: {kind: soak(env_id, kind, n) for kind in SCHEMES}
                  for env_id, n in (("heml_gym/TissueRetraction-v1", 1200), ("heml_gym/OrganRetraction-v2", 500))}
    result = {"machine": machine_info(), "wall_s": time.perf_counter() - start, "steps_s": list(steps),
              "order_errors_m": order, "reaction_N": reaction, "reaction_deviation_of_peak": deviation,
              "robustness": robustness, "command": "python benchmarks/accuracy/time_schemes.py"}
    write_json("time_schemes.json", result)
    (RESULTS / "time_schemes.md").write_text(markdown(result))
    chart(result, IMAGES / "time_schemes.png")
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    steps, order = r["steps_s"], r["order_errors_m"]
    rows = []
    for kind, errs in order.items():
        ratios = [f"{a / b:.2f}" for a, b in zip(errs, errs[1:])]
        rows.append([kind] + [f"{e:.2e}" for e in errs] + [" / ".join(ratios)])
    md = (f"Generated by `{r['command']}` in {r['wall_s']:.0f} s on {r['machine']['cpu']} "
          f"({r['machine']['date']}). Method: the script's docstring; discussion: "
          "[dynamics.md](../studies/dynamics.md#implicit-backward-euler-or-bdf2-quasi-newton-the-environments-default).\n\n"
          "**Order of accuracy** (the released slab: largest vertex error after 0.2 s, m, against the explicit "
          "solver at 0.05 of its critical step; ratio: the error's fall when the step halves, 2 for first order, "
          "4 for second; the reference's own error, first order in its tiny step, bounds the last ratio):\n\n")
    md += markdown_table(["scheme"] + [f"h = {1e3 * h:g} ms" for h in steps] + ["ratios"], rows)
    md += ("\n**Under-resolved motion** (the pulled slab sagging from flat: the held end's vertical reaction per "
           "0.05 s env step, mN; deviation: the largest from the explicit solver's, in % of its peak):\n\n")
    keys = list(r["reaction_N"])
    n = len(r["reaction_N"]["explicit"])
    md += markdown_table(["env step"] + keys,
                         [[k + 1] + [f"{1e3 * r['reaction_N'][key][k]:.1f}" for key in keys] for k in range(n)]
                         + [["deviation"] + ["-"] + [f"{100 * r['reaction_deviation_of_peak'][key]:.1f} %"
                                                      for key in keys[1:]]])
    md += ("\n**Robustness on the env scenes** (default physics under each scheme, 16 scenes, the same actions; "
           "every third env step extreme):\n\n")
    md += markdown_table(["env", "scheme", "env steps", "unconverged", "diverged", "re-taken shorter", "non-finite",
                          "episodes"],
                         [[env_id.split("/")[-1], kind, c["env_steps"], c["unconverged"], c["diverged"], c["refined"],
                           c["non_finite"], c["episodes"]]
                          for env_id, by in r["robustness"].items() for kind, c in by.items()])
    md += "\n![error against step, and the reaction per env step](../img/time_schemes.png)\n"
    return md


def chart(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    h = np.array(r["steps_s"]) * 1e3
    for kind, errs in r["order_errors_m"].items():
        a.loglog(h, np.array(errs) * 1e3, "o-", label=kind)
    a.loglog(h, r["order_errors_m"]["backward_euler"][0] * 1e3 * h / h[0], "k:", lw=0.8, label="slope 1")
    a.loglog(h, r["order_errors_m"]["bdf2"][0] * 1e3 * (h / h[0]) ** 2, "k--", lw=0.8, label="slope 2")
    a.set_xticks(h, [f"{v:g}" for v in h])
    a.minorticks_off()
    a.set_xlabel("step h (ms)")
    a.set_ylabel("largest vertex error after 0.2 s (mm)")
    a.set_title("released slab: order of accuracy")
    a.legend(fontsize=8)
    for key, series in r["reaction_N"].items():
        style = "k-" if key == "explicit" else ("--" if "8" in key else "-")
        b.plot(np.arange(1, len(series) + 1), np.array(series) * 1e3, style, marker=".", label=key)
    b.set_xlabel("env step (0.05 s)")
    b.set_ylabel("held end's vertical reaction (mN)")
    b.set_title("pulled slab sagging from flat")
    b.legend(fontsize=8)
    fig.suptitle(f"{r['machine']['cpu']}, {r['machine']['date']}", fontsize=8)
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
