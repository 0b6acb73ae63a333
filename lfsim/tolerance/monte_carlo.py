"""`lfsim tolerance`: Monte Carlo over a design's ``[tolerance]`` errors, sensitivity table and yield.

Units of work, all evaluated by :class:`~lfsim.tolerance.trial.TrialEvaluator`
on Dask (:mod:`lfsim.tolerance.execute`):

* ``nominal``: the design itself (compensators re-solved too: their merit
  is already met, so they stay);
* ``sens:<i>:+`` and ``sens:<i>:-``: tolerance i alone at ± its limit;
* ``mc:<n>``: Monte Carlo trial n, every tolerance drawn (:func:`~lfsim.tolerance.perturb.draw`).

``DIR/sensitivity.jsonl`` and ``DIR/trials.jsonl`` receive one record per
finished unit as it arrives (:class:`~lfsim.tolerance.store.RecordStore`);
``DIR/run.json`` fingerprints the run (design table, seed). ``resume=True``
evaluates only the units missing from the stores, after checking the
fingerprint; a larger ``trials`` extends a finished run. ``DIR/summary.json``,
``DIR/sensitivity.csv`` and the plots are written at the end.

Yield: the fraction of finished Monte Carlo trials meeting every target of
``[tolerance.targets]`` (a trial whose design fails to build or whose rays
fail where a metric needs them fails), with its Wilson 95 % interval.

Sensitivity: each tolerance's effect at ± its limit on every metric, and
``margin_used``, the largest over targets and both signs of
(degradation of the metric) / (nominal margin to the target); 1 means one
tolerance alone at its limit uses the whole margin. Tolerances are ranked by
it. From the Monte Carlo trials, ``mc_variance_share``: a least-squares fit
of each targeted metric on the drawn offsets; a tolerance's share is its
term's variance over the sum of all terms' (of the metric with the smallest
yield), an independent check of the ranking that includes the actual
distributions.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np

from ..design.design import Design
from ..design.errors import DesignError
from ..design.tolerance_section import TARGETS, ToleranceSpec, tolerance_from_design
from ..fileio import write_json, write_text
from . import execute
from .perturb import draw, perturb
from .store import RecordStore
from .trial import METRICS, with_sampling


class RunMismatch(ValueError):
    """``--resume`` on a directory that holds a different run."""


def fingerprint(raw: dict, seed: int) -> str:
    """Hash of what determines every record: the design table (less ``tolerance.trials``) and the seed."""
    tab = json.loads(json.dumps(raw, default=str))
    tab.get("tolerance", {}).pop("trials", None)
    tab.get("tolerance", {}).pop("batch", None)
    text = json.dumps({"design": tab, "seed": int(seed)}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def spec_of(design: Design) -> ToleranceSpec:
    spec = tolerance_from_design(design)
    if spec is None or not spec.parameters:
        raise DesignError(design.path or "<dict>", "tolerance.parameters", None,
                          "required: a [tolerance] section with [[tolerance.parameters]]")
    return spec


def preflight(design: Design, spec: ToleranceSpec) -> None:
    """Each tolerance at ± its limit must give a valid design (else a DesignError naming it)."""
    for i, t in enumerate(spec.parameters):
        for sgn in (1.0, -1.0):
            try:
                Design.from_dict(perturb(design.raw, spec, {t.name: sgn * t.limit}, design.path or "<dict>"),
                                 design.path or "<dict>")
            except DesignError as e:
                raise DesignError(design.path or "<dict>", f"tolerance.parameters[{i}].limit", t.limit,
                                  f"{t.name} at {sgn * t.limit:+g} is not a valid design ({e.allowed})") from None


def units_for(spec: ToleranceSpec, seed: int, trials: int, sensitivity: bool = True):
    """(sensitivity units, Monte Carlo units): lists of (uid, offsets)."""
    sens = [("nominal", {})]
    if sensitivity:
        for i, t in enumerate(spec.parameters):
            sens += [(f"sens:{i}:+", {t.name: t.limit}), (f"sens:{i}:-", {t.name: -t.limit})]
    mc = [(f"mc:{n}", draw(spec, seed, n)) for n in range(trials)]
    return sens, mc


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float] | None:
    """Wilson score 95 % interval of a proportion k/n."""
    if n == 0:
        return None
    p = k / n
    den = 1.0 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def _degradation(kind: str, value, nominal) -> float:
    if value is None:
        return math.inf
    return (value - nominal) if kind == "max" else (nominal - value)


def sensitivity_table(spec: ToleranceSpec, records: dict) -> list[dict]:
    """Rows (one per tolerance), ranked by ``margin_used``."""
    nom = records.get("nominal")
    m0 = (nom or {}).get("metrics") or {}
    rows = []
    for i, t in enumerate(spec.parameters):
        plus, minus = records.get(f"sens:{i}:+"), records.get(f"sens:{i}:-")
        row = {"name": t.name, "keys": list(t.keys), "rigid": list(t.rigid), "motion": t.motion,
               "limit": t.limit, "relative": t.relative, "distribution": t.distribution, "sigma": t.sigma,
               "plus": (plus or {}).get("metrics"), "minus": (minus or {}).get("metrics"),
               "errors": [r["error"] for r in (plus, minus) if r and r.get("error")],
               "delta": {}, "margin_used": None, "worst_target": None}
        for key in METRICS:
            ds = [r["metrics"][key] - m0[key] for r in (plus, minus)
                  if r and r.get("metrics") and r["metrics"].get(key) is not None and m0.get(key) is not None]
            row["delta"][key] = {"plus": ds[0] if len(ds) == 2 else None, "minus": ds[1] if len(ds) == 2 else None}
        worst, where = None, None
        if nom and m0:
            for name, limit in spec.targets.items():
                kind, key = TARGETS[name]
                if m0.get(key) is None:
                    continue
                margin = (limit - m0[key]) if kind == "max" else (m0[key] - limit)
                for r in (plus, minus):
                    if r is None:
                        continue
                    v = (r.get("metrics") or {}).get(key)
                    deg = _degradation(kind, v, m0[key])
                    used = deg / margin if margin > 0 else (math.inf if deg > 0 else 0.0)
                    if worst is None or used > worst:
                        worst, where = used, name
        row["margin_used"] = None if worst is None or not math.isfinite(worst) else worst
        row["margin_used_inf"] = worst is not None and not math.isfinite(worst)
        row["worst_target"] = where
        rows.append(row)
    rows.sort(key=lambda r: -(math.inf if r["margin_used_inf"] else (r["margin_used"] or 0.0)))
    for rank, r in enumerate(rows, 1):
        r["rank"] = rank
    return rows


def variance_shares(spec: ToleranceSpec, mc: list[dict], metric: str) -> dict[str, float] | None:
    """Share of each tolerance in the linear fit of ``metric`` on the offsets (Monte Carlo)."""
    ok = [r for r in mc if r.get("metrics") and r["metrics"].get(metric) is not None]
    names = list(spec.names)
    if len(ok) < len(names) + 2:
        return None
    X = np.array([[r["offsets"].get(n, 0.0) for n in names] for r in ok])
    y = np.array([r["metrics"][metric] for r in ok])
    A = np.column_stack([np.ones(len(ok)), X])
    beta = np.linalg.lstsq(A, y, rcond=None)[0][1:]
    terms = beta ** 2 * X.var(axis=0)
    tot = terms.sum()
    if not tot > 0:
        return None
    return {n: float(v / tot) for n, v in zip(names, terms)}


def _stats(values: list[float]) -> dict | None:
    v = np.array([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return None
    p = np.percentile(v, [5, 50, 95])
    return {"mean": float(v.mean()), "std": float(v.std()), "min": float(v.min()), "max": float(v.max()),
            "p5": float(p[0]), "p50": float(p[1]), "p95": float(p[2])}


def summarize_run(design: Design, spec: ToleranceSpec, sens: RecordStore, mc_store: RecordStore,
                  trials: int, seed: int, seconds: float, where: dict) -> dict:
    mc = [mc_store.records[f"mc:{n}"] for n in range(trials) if f"mc:{n}" in mc_store]
    n = len(mc)
    k = sum(1 for r in mc if r["pass"])
    per_target = {}
    for name in spec.targets:
        kk = sum(1 for r in mc if name not in r["failed"] and "error" not in r["failed"])
        per_target[name] = kk / n if n else None
    rows = sensitivity_table(spec, sens.records)
    nominal = sens.records.get("nominal", {})
    worst_target = min(per_target, key=lambda t: per_target[t]) if per_target and n else None
    share = variance_shares(spec, mc, TARGETS[worst_target][1]) if worst_target else None
    for r in rows:
        r["mc_variance_share"] = None if share is None else share.get(r["name"])
    times = [r["seconds"] for r in mc]
    return {
        "design": design.name, "file": design.path, "trials": n, "trials_requested": trials, "seed": seed,
        "yield": k / n if n else None, "yield_ci95": wilson(k, n), "passed": k,
        "errors": sum(1 for r in mc if r.get("error")),
        "yield_by_target": per_target, "limiting_target": worst_target,
        "targets": spec.targets, "nominal": nominal.get("metrics"), "nominal_pass": nominal.get("pass"),
        "nominal_compensators": nominal.get("compensators"),
        "metrics": {m: _stats([(r.get("metrics") or {}).get(m) for r in mc]) for m in METRICS},
        "sensitivity": rows,
        "dominant": [r["name"] for r in rows[:3]],
        "compensators": list(spec.compensators), "compensator_method": spec.compensator_method,
        "sampling": {k2: (list(v) if isinstance(v, tuple) else v) for k2, v in spec.sampling.items()},
        "seconds": round(seconds, 2), "trial_seconds_mean": float(np.mean(times)) if times else None,
        "execution": where,
    }


def _csv(rows: list[dict]) -> str:
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf)
    keys = ["gd_max_deg", "pa_max", "contrast_nyquist_min", "rms_spot_mean_arcmin"]
    w.writerow(["rank", "name", "limit", "distribution", "margin_used", "worst_target", "mc_variance_share"]
               + [f"d_{k}_{s}" for k in keys for s in ("plus", "minus")])
    for r in rows:
        w.writerow([r["rank"], r["name"], r["limit"], r["distribution"],
                    "inf" if r["margin_used_inf"] else r["margin_used"], r["worst_target"],
                    r["mc_variance_share"]] + [r["delta"][k][s] for k in keys for s in ("plus", "minus")])
    return buf.getvalue()


def run_tolerance(design: Design, out_dir, trials: int | None = None, seed: int | None = None,
                  scheduler: str | None = None, workers: int | None = None, serial: bool = False,
                  resume: bool = False, batch: int | None = None, sensitivity: bool = True,
                  plots: bool = True, progress: bool = False, log=None) -> dict:
    """Run (or resume) a tolerance analysis; returns the ``summary.json`` document."""
    spec = spec_of(design)
    trials = int(trials if trials is not None else spec.trials)
    seed = int(seed if seed is not None else spec.seed)
    batch = int(batch or spec.batch)
    if trials < 1 or seed < 0 or batch < 1:
        raise ValueError(f"trials = {trials}, seed = {seed}, batch = {batch}: need trials >= 1, seed >= 0, batch >= 1")
    preflight(design, spec)
    from .. import budget
    from .execute import BYTES_PER_RECORD

    budget.check(budget.Estimate(f"tolerance run of {trials:,} trials", 0.0,
                                 budget.BASE_BYTES + BYTES_PER_RECORD * trials), hint="lower --trials")
    out = Path(out_dir)
    fp = fingerprint(design.raw, seed)
    run_file = out / "run.json"
    sens = RecordStore(out / "sensitivity.jsonl").load()
    mc_store = RecordStore(out / "trials.jsonl").load()
    if resume and not (run_file.exists() or len(sens) or len(mc_store)):
        raise RunMismatch(f"{out}: --resume, but the folder holds no tolerance run (no run.json or trial "
                          "records): drop --resume to start one")
    if run_file.exists() or len(sens) or len(mc_store):
        old = json.loads(run_file.read_text()) if run_file.exists() else {}
        if not resume:
            raise RunMismatch(f"{out}: holds a tolerance run ({len(mc_store)} trials): pass --resume to continue "
                              "it, or choose another --out")
        if old.get("fingerprint") != fp:
            raise RunMismatch(f"{out}: holds a run of another design or seed (fingerprint {old.get('fingerprint')} "
                              f"!= {fp}): choose another --out")
    created = not out.exists()
    fresh = not (run_file.exists() or len(sens) or len(mc_store))  # this call starts the run
    write_json(run_file, {"design": design.path, "fingerprint": fp, "seed": seed,
                          "tolerances": list(spec.names), "compensators": list(spec.compensators)})
    sens_units, mc_units = units_for(spec, seed, trials, sensitivity)
    todo = [u for u in sens_units if u[0] not in sens] + [u for u in mc_units if u[0] not in mc_store]
    job = {"kind": "tolerance", "key": fp, "raw": design.raw, "path": design.path or "<dict>", "spec": spec,
           "threads": None}
    bar = None
    if progress:
        from ..progress import bar as tqdm

        bar = tqdm(total=len(sens_units) + len(mc_units), initial=len(sens_units) + len(mc_units) - len(todo),
                   desc=f"trials ({len(mc_units)}) and ±limit runs ({len(sens_units)})", unit="run")

    def on_records(recs):
        for rec in recs:
            (mc_store if rec["id"].startswith("mc:") else sens).add([rec])
        if bar:
            bar.update(len(recs))
            done = [r for r in mc_store.records.values()]
            if done:
                bar.set_postfix(yield_=f"{sum(r['pass'] for r in done) / len(done):.3f}")

    t0 = time.perf_counter()
    where = {"mode": "none", "scheduler": None, "workers": 0}
    try:
        if todo:
            where = execute.run(job, todo, batch=batch, scheduler=scheduler, workers=workers, serial=serial,
                                on_records=on_records, estimate="tolerance trials and ±limit runs", log=log)
    except budget.BudgetError:  # refused after the probe: a run this call started leaves nothing behind
        if fresh:
            for f in (run_file, out / "sensitivity.jsonl", out / "trials.jsonl"):
                f.unlink(missing_ok=True)
            if created and out.is_dir() and not any(out.iterdir()):
                out.rmdir()
        raise
    finally:
        if bar:
            bar.close()
    seconds = time.perf_counter() - t0
    doc = summarize_run(design, spec, sens, mc_store, trials, seed, seconds, where)
    doc["units_evaluated"] = len(todo)
    doc["trials_per_second"] = (len(todo) / seconds) if todo and seconds > 0 else None
    doc["duplicates_dropped"] = sens.duplicates + mc_store.duplicates
    if plots:
        from ..analysis.tolerance_plots import write_all

        mc = [mc_store.records[f"mc:{n}"] for n in range(trials) if f"mc:{n}" in mc_store]
        doc["plots"] = write_all(doc, mc, out)
    write_text(out / "sensitivity.csv", _csv(doc["sensitivity"]))
    write_json(out / "summary.json", doc)
    return doc


def sampled_design(design: Design, spec: ToleranceSpec) -> Design:
    """The nominal design with the run's metric sampling (for comparisons with full sampling)."""
    return Design.from_dict(with_sampling(design.raw, spec.sampling), design.path or "<dict>")
