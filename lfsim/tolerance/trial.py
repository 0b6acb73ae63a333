"""One trial: perturb the nominal design, re-solve the compensators, measure the InI metrics.

A :class:`TrialEvaluator` is built once per process (per worker) and job: it
holds the nominal design with the run's metric sampling written into its
``[ini.analysis]``, the nominal :class:`~lfsim.ini.model.IniModel` (the
reference of GD and PA: a built unit shows the elemental images laid out for
the nominal design) and the sampled sub-systems. Dr.Jit compiles each kernel
the first time a process meets it and reuses it for every later trial of the
same design (same shapes, new parameter values), so a worker pays the
compilation once.
"""

from __future__ import annotations

import copy
import os
import socket
import time

from ..analysis.ini_analysis import PupilSets, evaluate, summarize
from ..design.design import Design
from ..design.errors import DesignError
from ..design.tolerance_section import TARGETS, ToleranceSpec
from ..ini.model import IniModel, IniModelError
from ..ini.subsystems import sample, trace_many
from .compensate import compensate, paraxial_depths
from .perturb import apply_setting_errors, perturb

#: Metrics recorded per trial (keys of ``lfsim analyze``'s summary).
METRICS = ("gd_max_deg", "gd_mean_deg", "pa_max", "pa_mean", "contrast_nyquist_min", "contrast_nyquist_mean",
           "rms_spot_mean_arcmin")


def with_sampling(raw: dict, sampling: dict) -> dict:
    """A copy of ``raw`` whose ``[ini.analysis]`` holds the run's metric sampling."""
    out = copy.deepcopy(raw)
    ana = dict(out["ini"].get("analysis", {}))
    ana.update(stride=list(sampling["stride"]), fields=int(sampling["fields"]), pupil=int(sampling["pupil"]),
               mtf_grid=int(sampling["mtf_grid"]), refine=int(sampling["refine"]), symmetry="none")
    out["ini"]["analysis"] = ana
    return out


def metrics_of(design: Design, reference: IniModel | None = None, subs=None) -> dict:
    """The InI metrics of ``design`` (its ``[ini.analysis]`` sampling), GD/PA against ``reference``."""
    model = IniModel(design)
    ref = reference or model
    return _summary(evaluate(model, subs if subs is not None else sample(ref), reference=reference))


def _summary(res: dict) -> dict:
    s = summarize(res, package=False)["summary"]
    out = {k: s[k] for k in METRICS}
    out["rays_failed"] = s["rays_failed"]
    return out


def passes(metrics: dict, targets: dict) -> list[str]:
    """Names of the targets a trial misses (a missing metric misses)."""
    failed = []
    for name, limit in targets.items():
        kind, key = TARGETS[name]
        v = metrics.get(key)
        if v is None or (kind == "max" and not v <= limit) or (kind == "min" and not v >= limit):
            failed.append(name)
    return failed


class TrialEvaluator:
    """Evaluates trials of one design and tolerance spec (see the module docstring)."""

    def __init__(self, raw: dict, path: str, spec: ToleranceSpec):
        self.spec = spec
        self.path = path
        self.raw0 = with_sampling(raw, spec.sampling)
        self.nominal = Design.from_dict(self.raw0, path)
        self.ref = IniModel(self.nominal)
        self.subs = sample(self.ref)
        self.target_depths = paraxial_depths(self.ref)

    def build(self, offsets: dict[str, float]):
        """(the built unit: perturbed, compensated, with setting errors; the Compensation)."""
        raw = perturb(self.raw0, self.spec, offsets, self.path)
        design = Design.from_dict(raw, self.path)
        comp = compensate(design, self.spec.compensators, self.spec.compensator_method, self.target_depths,
                          self.spec.compensator_iterations, self.spec.sampling)
        raw_c = apply_setting_errors(comp.design.raw, self.spec, offsets, self.path)
        design_c = comp.design if raw_c is comp.design.raw else Design.from_dict(raw_c, self.path)
        return design_c, comp

    def run(self, uid: str, offsets: dict[str, float]) -> dict:
        """The record of one trial: offsets, compensator values, metrics, pass/fail (or its error)."""
        return self.run_many([(uid, offsets)])[0]

    def run_many(self, units: list) -> list[dict]:
        """The records of several trials ``[(uid, offsets)]``, their rays traced in shared launches.

        Each unit is built (perturbed, compensated) and modelled on its own;
        the rays of every sampled sub-system of all of them are then aimed and
        traced together (:func:`lfsim.ini.subsystems.trace_many`: one kernel
        launch per Newton step for the whole batch, bit for bit the rays each
        would get alone), and each unit's metrics are computed from its rays.
        A unit whose design or model fails is a recorded, failed trial.
        ``seconds`` of a record: its own build and metrics plus its share of
        the shared trace.
        """
        recs, built = [], []
        for uid, offsets in units:
            t0 = time.perf_counter()
            rec = {"id": uid, "offsets": dict(offsets), "compensators": {}, "metrics": None, "pass": False,
                   "failed": [], "error": None}
            try:
                design_c, comp = self.build(offsets)
                rec["compensators"] = comp.values
                rec["compensator_cost"] = [comp.cost0, comp.cost]
                built.append((rec, IniModel(design_c)))
            except _ERRORS as e:
                _fail(rec, e)
            rec["seconds"] = time.perf_counter() - t0
            recs.append(rec)
        if built:
            t0 = time.perf_counter()
            sets = PupilSets.build(self.nominal.ini.pupil, self.nominal.ini.mtf_grid)
            bundles = trace_many([mo for _, mo in built], self.subs, sets.rho)
            share = (time.perf_counter() - t0) / len(built)
            for (rec, model), bundle in zip(built, bundles):
                t1 = time.perf_counter()
                try:
                    rec["metrics"] = _summary(evaluate(model, self.subs, reference=self.ref, bundle=bundle))
                    rec["failed"] = passes(rec["metrics"], self.spec.targets)
                    rec["pass"] = not rec["failed"]
                except _ERRORS as e:
                    _fail(rec, e)
                rec["seconds"] += share + time.perf_counter() - t1
        worker = f"{socket.gethostname()}:{os.getpid()}"
        for rec in recs:
            rec["seconds"] = round(rec["seconds"], 4)
            rec["worker"] = worker
        return recs


_ERRORS = (DesignError, IniModelError, ValueError, FloatingPointError)


def _fail(rec: dict, e: Exception) -> None:
    rec["metrics"] = None
    rec["error"] = " ".join(str(e).split())[:300]
    rec["failed"] = ["error"]
