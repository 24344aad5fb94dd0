"""A numerical check of Proposition 1 (paper section 3.1, proof in appendix A.2).

The proposition models a random agent's progress as S_N = X_1 + ... + X_N with i.i.d.
X_i = +1 or -1 with probability 1/2 each, and states P(S_N >= alpha N) <= exp(-N beta)
"where alpha > 1/2", with (appendix A.2) beta = log(1/(1-alpha)) + alpha log(alpha/(1-alpha)).

We simulate ``walks`` random walks of ``n_max`` +-1 steps, estimate P(S_N >= alpha N) for
every N = 1..n_max and several alpha, compute the same probability exactly (binomial
tail), and compare with three exponents:

* ``chernoff_pm1``: the correct Chernoff bound for +-1 steps. The optimal theta is
  atanh(alpha) and beta(alpha) = (1+alpha)/2 log(1+alpha) + (1-alpha)/2 log(1-alpha)
  (= the KL divergence of Bernoulli((1+alpha)/2) from Bernoulli(1/2)). It holds for every
  N and every 0 < alpha <= 1 (alpha = 1 gives 2^-N, which is exact).
* ``paper_literal``: the paper's beta as written, at the same alpha (the statement reads
  X in {-1, +1}); the paper only claims it for alpha > 1/2.
* ``paper_01``: the paper's beta as written, read the way its proof computes the moment
  generating function ((1 + e^theta)/2 is that of X in {0, 1}): the event S_N >= alpha N
  for +-1 steps is the event H_N >= alpha' N for the number of +1 steps H_N, with
  alpha' = (1 + alpha)/2 > 1/2, so this is the paper's formula at alpha'.

For X in {0, 1} the correct Chernoff exponent at alpha' is log 2 + alpha' log alpha' +
(1 - alpha') log(1 - alpha'), which equals ``chernoff_pm1`` at alpha; the paper's formula
has log(1/(1-alpha)) where substituting theta* gives log(2 (1 - alpha)).
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.stats import binom

from .common import machine, provenance, pyplot, save_figure, write_json

EPS = 1e-9  # S_N >= alpha N is tested as S_N >= alpha N - EPS (alpha N is a float)


@dataclass
class Prop1Config:
    alphas: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.5, 0.7])
    n_max: int = 100
    walks: int = 1_000_000
    seed: int = 0
    chunk: int = 100_000
    z: float = 4.0  # Monte-Carlo tolerance in standard errors when judging a violation

    def validate(self) -> None:
        if not self.alphas or any(not (0 < a <= 1) for a in self.alphas):
            raise ValueError(f"alphas must lie in (0, 1], got {self.alphas}")
        for name, least in (("n_max", 1), ("walks", 2), ("chunk", 1)):
            if getattr(self, name) < least:
                raise ValueError(f"{name} must be >= {least}, got {getattr(self, name)}")


# ------------------------------------------------------------------------ exponents
def beta_pm1(alpha: float) -> float:
    """Correct Chernoff exponent for P(S_N >= alpha N), X = +-1 with p = 1/2."""
    a = float(alpha)
    if not (0 < a <= 1):
        raise ValueError(f"alpha must be in (0, 1], got {a}")
    t = (1 - a) / 2 * math.log(1 - a) if a < 1 else 0.0
    return (1 + a) / 2 * math.log(1 + a) + t


def beta_01(alpha: float) -> float:
    """Correct Chernoff exponent for P(H_N >= alpha N), X in {0, 1} with p = 1/2 (alpha > 1/2)."""
    a = float(alpha)
    t = (1 - a) * math.log(1 - a) if a < 1 else 0.0
    return math.log(2) + a * math.log(a) + t


def beta_paper(alpha: float) -> float:
    """The paper's beta as written: log(1/(1-alpha)) + alpha log(alpha/(1-alpha)); alpha in (0, 1)."""
    a = float(alpha)
    if not (0 < a < 1):
        return math.inf if a == 1 else math.nan
    return math.log(1 / (1 - a)) + a * math.log(a / (1 - a))


# ------------------------------------------------------------------------ probabilities
def exact_tail(ns: np.ndarray, alpha: float) -> np.ndarray:
    """P(S_N >= alpha N) exactly: S_N = 2 H_N - N with H_N ~ Binomial(N, 1/2)."""
    k = np.ceil((1 + alpha) * ns / 2 - EPS).astype(np.int64)  # smallest H_N with 2H - N >= alpha N
    return binom.sf(k - 1, ns, 0.5)


def simulate(cfg: Prop1Config) -> np.ndarray:
    """Counts (len(alphas), n_max) of walks with S_N >= alpha N."""
    rng = np.random.default_rng(cfg.seed)
    ns = np.arange(1, cfg.n_max + 1)
    thr = np.array([a * ns - EPS for a in cfg.alphas])  # (A, n_max)
    counts = np.zeros((len(cfg.alphas), cfg.n_max), np.int64)
    done = 0
    while done < cfg.walks:
        m = min(cfg.chunk, cfg.walks - done)
        steps = rng.integers(0, 2, size=(m, cfg.n_max), dtype=np.int8) * np.int8(2) - np.int8(1)
        s = np.cumsum(steps, axis=1, dtype=np.int16)
        for i in range(len(cfg.alphas)):
            counts[i] += (s >= thr[i]).sum(axis=0)
        done += m
    return counts


def run_prop1(cfg: Prop1Config) -> dict:
    cfg.validate()
    t0 = time.perf_counter()
    ns = np.arange(1, cfg.n_max + 1)
    counts = simulate(cfg)
    t1 = time.perf_counter()
    per_alpha = []
    for i, a in enumerate(cfg.alphas):
        emp = counts[i] / cfg.walks
        se = np.sqrt(np.maximum(emp * (1 - emp), 0) / cfg.walks)
        exact = exact_tail(ns, a)
        a01 = (1 + a) / 2
        bounds = {
            "chernoff_pm1": {"beta": beta_pm1(a), "alpha_used": a},
            "paper_literal": {"beta": beta_paper(a), "alpha_used": a, "paper_claims_it": a > 0.5},
            "paper_01": {"beta": beta_paper(a01), "alpha_used": a01, "paper_claims_it": a01 > 0.5},
        }
        for b in bounds.values():
            beta = b["beta"]
            bound = np.exp(-ns * beta) if math.isfinite(beta) else np.full(len(ns), math.nan)
            # A bound >= 1 says nothing; a violation is judged on the exact probability and, for the
            # Monte-Carlo estimate, beyond z standard errors (plus one walk's worth of slack).
            tol = cfg.z * np.maximum(se, np.sqrt(bound * (1 - np.minimum(bound, 1)) / cfg.walks)) + 1 / cfg.walks
            b["bound"] = bound
            b["informative"] = bool(np.all(bound < 1)) if math.isfinite(beta) else False
            b["exact_violations_N"] = ns[exact > bound * (1 + 1e-12)].tolist()
            b["empirical_violations_N"] = ns[emp > bound + tol].tolist()
            b["max_ratio_exact_over_bound"] = float(np.max(exact / bound)) if math.isfinite(beta) else None
        per_alpha.append({
            "alpha": a, "alpha_01": a01, "empirical": emp, "empirical_se": se, "exact": exact,
            # Monte-Carlo error in units of the exact probability's binomial standard error.
            "empirical_minus_exact_in_se": (emp - exact) / np.sqrt(np.maximum(exact * (1 - exact), 1e-300) / cfg.walks),
            "bounds": bounds,
        })
    res = {
        "experiment": "prop1",
        "description": "P(S_N >= alpha N) for +-1 random walks (p = 1/2) vs Chernoff bounds exp(-N beta)",
        "config": asdict(cfg),
        "N": ns,
        "per_alpha": per_alpha,
        "beta_curves": _beta_curves(),
        "notes": {
            "chernoff_pm1": "beta = (1+a)/2 log(1+a) + (1-a)/2 log(1-a): correct for +-1 steps, any 0 < a <= 1",
            "paper_literal": "the paper's beta = log(1/(1-a)) + a log(a/(1-a)) at the same a (statement: X = +-1)",
            "paper_01": "the paper's beta at a' = (1+a)/2, the {0,1} reading of its proof (same event)",
            "violations": "N where the exact probability exceeds the bound, and where the Monte-Carlo "
                          f"estimate exceeds it by more than {cfg.z} standard errors",
        },
    }
    res["summary"] = {
        f"alpha={p['alpha']}": {k: {"exact_violations": len(b["exact_violations_N"]),
                                    "empirical_violations": len(b["empirical_violations_N"]),
                                    "informative": b["informative"]}
                                for k, b in p["bounds"].items()}
        for p in per_alpha}
    res["timing_seconds"] = {"simulation": t1 - t0, "total": time.perf_counter() - t0}
    res["machine"] = machine()
    res["provenance"] = provenance()
    return res


def _beta_curves() -> dict:
    a = np.round(np.linspace(0.01, 0.99, 99), 2)
    return {"alpha": a, "chernoff_pm1": [beta_pm1(x) for x in a], "paper_literal": [beta_paper(x) for x in a],
            "paper_01": [beta_paper((1 + x) / 2) for x in a], "chernoff_01_at_alpha": [beta_01(x) if x > 0.5
                                                                                    else None for x in a]}


# ------------------------------------------------------------------------ figure
def plot(res: dict, out_dir: Path) -> Path:
    plt = pyplot()
    ns = np.array(res["N"])
    W = res["config"]["walks"]
    pa = res["per_alpha"]
    cols = 3
    rows = math.ceil((len(pa) + 1) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    axes = axes.ravel()
    floor = 0.3 / W
    for ax, p in zip(axes, pa):
        emp = np.array(p["empirical"], float)
        ok = emp > 0
        ax.semilogy(ns, p["exact"], color="k", lw=1.2, label="exact P(S_N >= alpha N)")
        ax.semilogy(ns[ok], emp[ok], "o", ms=2.2, color="C0", label=f"Monte Carlo ({W:,} walks)")
        b = p["bounds"]
        ax.semilogy(ns, b["chernoff_pm1"]["bound"], color="C2", lw=1.5, ls="--",
                    label="correct Chernoff bound for +-1 steps")
        for key, c, lab in (("paper_literal", "C3", "paper's beta at alpha (statement, X = +-1)"),
                            ("paper_01", "C1", "paper's beta at (1+alpha)/2 (proof, X in {0,1})")):
            bb = np.array(b[key]["bound"], float)
            if np.all(np.isfinite(bb)):
                ax.semilogy(ns, bb, color=c, lw=1.2, ls=":", label=lab)
        ax.set_ylim(max(floor, 1e-12), 2)
        ax.set_title(f"alpha = {p['alpha']}: beta = {b['chernoff_pm1']['beta']:.3f} (correct), "
                     f"{b['paper_literal']['beta']:.3f} / {b['paper_01']['beta']:.3f} (paper)", fontsize=8.5)
        ax.set_xlabel("N")
        ax.set_ylabel("probability")
        ax.grid(alpha=0.3, which="both", lw=0.4)
    handles, labels = axes[0].get_legend_handles_labels()
    ax = axes[len(pa)]
    bc = res["beta_curves"]
    a = np.array(bc["alpha"])
    ax.plot(a, bc["chernoff_pm1"], color="C2", ls="--", label="correct, +-1 steps")
    ax.plot(a, np.array(bc["paper_literal"], float), color="C3", ls=":", label="paper's formula at a")
    ax.plot(a, bc["paper_01"], color="C1", ls=":", label="paper's formula at (1+a)/2")
    ax.axhline(0, color="grey", lw=0.8)
    ax.axvline(0.5, color="grey", lw=0.8, ls="-.")
    ax.set_ylim(-0.5, 3)
    ax.set_xlabel("alpha")
    ax.set_ylabel("beta (decay rate per step)")
    ax.set_title("exponents", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    for ax in axes[len(pa) + 1:]:
        ax.axis("off")
    fig.suptitle("Proposition 1: P(S_N >= alpha N) for a +-1 random walk (p = 1/2) against exp(-N beta)", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    path = save_figure(fig, out_dir / "prop1.png")
    plt.close(fig)
    return path


# ------------------------------------------------------------------------ CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Prop1Config()
    p.add_argument("--alphas", type=float, nargs="+", default=d.alphas, help="thresholds alpha in (0, 1]")
    p.add_argument("--n-max", type=int, default=d.n_max)
    p.add_argument("--walks", type=int, default=d.walks, help="Monte-Carlo random walks")
    p.add_argument("--chunk", type=int, default=d.chunk, help="walks simulated at once")


def config(args: argparse.Namespace) -> Prop1Config:
    return Prop1Config(alphas=list(args.alphas), n_max=args.n_max, walks=args.walks, seed=args.seed, chunk=args.chunk)


def check(args: argparse.Namespace) -> None:
    config(args).validate()


def main(args: argparse.Namespace, out_dir: Path) -> dict:
    res = run_prop1(config(args))
    write_json(out_dir / "prop1.json", res)
    fig = plot(res, out_dir)
    return {"files": [str(out_dir / "prop1.json"), str(fig)], "summary": res["summary"]}
