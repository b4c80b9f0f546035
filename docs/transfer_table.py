"""The transfer table of docs/analyze.md: a model fitted on one UR10 session, carried to the
other with only the tracker registration and the probe mount re-identified
(`keo analyze --registration-only`), judged on that session's held-out poses.

    python docs/transfer_table.py [--data data/ur10_lasertracker] [--work DIR] [--json]
        [--decompose]

Imports both series (as `keo import ur10-lasertracker` does), analyzes each, then carries each
model to the other series. Prints one row per direction: held-out position RMS (and max) of
the carried model, the nominal robot's held-out RMS there, and the other session's own model.
Rerun it after every change to the fit: this table is what the change is judged on.

`--decompose` also says what each carried figure is made of (docs/analyze.md, "What A on B
is made of"): the held-out poses by where they lie against the model's calibrated joint
ranges (inside, in the maps' fade, beyond it), the figure with each effect left out, each
joint's map or periodic terms left out, and each joint's joint-angle function (its periodic
terms and its map) replaced by the other series' own; the registration and the probe mount
refitted every time, as `--registration-only` does. And what the model's own series says
(docs/analyze.md, "What A's data determine"): its own held-out poses with each joint's
function from the other series, how much the other joints' maps inflate each map's variance
on its poses, and its maps fitted on each half of the series in time and carried to the other.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "ur10_lasertracker.toml"
SERIES = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
}


def _quiet(fn: Any, *args: Any, **kw: Any) -> Any:
    """Run `fn` with its progress lines (stderr) kept, so the table stays readable."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        return fn(*args, **kw)


def _location(q: np.ndarray, model: Any, error_mm: np.ndarray) -> list[dict[str, Any]]:
    """The held-out poses by where they lie against the model's calibrated joint ranges: every
    joint inside, the farthest joint within the maps' fade, beyond it."""
    lo, hi = np.asarray(model.calibrated_q_min), np.asarray(model.calibrated_q_max)
    taper = 0.1 if model.map_taper_rad is None else model.map_taper_rad
    far = np.max(np.maximum(lo - q, 0.0) + np.maximum(q - hi, 0.0), axis=1)
    where = np.where(far == 0, 0, np.where(far < taper, 1, 2))
    out = []
    labels = ("every joint inside", "farthest joint in the maps' fade", "beyond the fade")
    for k, label in enumerate(labels):
        sel = where == k
        if sel.any():
            rms = float(np.sqrt(np.mean(error_mm[sel] ** 2)))
            out.append({"where": label, "poses": int(sel.sum()), "pos_rms_mm": rms})
    return out


def _swapped(parts: list[Any], other: dict[str, Any], joint: int, drop: str) -> Any:
    """The carried model's effects with `drop` ("effect NAME", "map", "ripple", "function")
    applied to `joint` (-1 for a whole effect): left out, or ("function") joint's periodic terms
    and map taken from `other` (name -> (effect, values))."""
    from keo_service.fit.effects import JointMaps, JointRipple, split_maps

    effects: list[Any] = []
    values: list[np.ndarray] = []
    for effect, part in parts:
        if drop == f"effect {effect.name}":
            continue
        if isinstance(effect, JointMaps) and drop in ("map", "function"):
            pieces = list(split_maps(effect.knots, part))
            empty = (np.empty(0), np.empty(0))
            if drop == "map" or "joint_maps" not in other:
                pieces[joint] = empty
            else:
                theirs = split_maps(other["joint_maps"][0].knots, other["joint_maps"][1])
                pieces[joint] = theirs[joint]
            effects.append(JointMaps(tuple(k for k, _v in pieces), effect.taper))
            values.append(np.concatenate([v for _k, v in pieces]))
            continue
        if isinstance(effect, JointRipple) and drop in ("ripple", "function"):
            keep = [i for i, (j, _p) in enumerate(effect.terms) if j != joint]
            terms = [effect.terms[i] for i in keep]
            vals = [part[2 * i : 2 * i + 2] for i in keep]
            if drop == "function" and "joint_ripple" in other:
                theirs, their_values = other["joint_ripple"]
                for i, (j, period) in enumerate(theirs.terms):
                    if j == joint:
                        terms.append((j, period))
                        vals.append(their_values[2 * i : 2 * i + 2])
            if terms:
                effects.append(JointRipple(tuple(terms)))
                values.append(np.concatenate(vals))
            continue
        effects.append(effect)
        values.append(part)
    return effects, values


def decompose(work: Path, src: str, dst: str) -> dict[str, Any]:
    """What the model of `src` carried to `dst` is made of, on `dst`'s held-out poses (see the
    module's doc): each variant's registration and mount refitted on `dst`'s training rows."""
    from keo_service.core.chain import Chain
    from keo_service.io.analysis_report import saved_model
    from keo_service.io.cell import robot_from_config
    from keo_service.io.config import load_config

    config = load_config(work / src / "an" / "model.toml")
    robot = robot_from_config(config)
    chain = Chain(robot)
    carried = _Session.of(work, dst, config, chain)
    model, x, position_only, val = carried.model, carried.x, carried.position_only, carried.val
    held_out = carried.held_out

    parts = list(model.parts(x))
    source = _source_side(work, src, config, robot)
    own = load_config(work / dst / "an" / "model.toml")
    theirs_model = saved_model(own, chain, position_only)
    theirs = {e.name: (e, v) for e, v in theirs_model.parts(theirs_model.x)}
    names = robot.joint_names
    full = carried.errors_mm(model, x)
    out: dict[str, Any] = {
        "model_from": src,
        "applied_to": dst,
        "held_out_pos_rms_mm": float(np.sqrt(np.mean(full**2))),
        "where": _location(val.q, config.model, full),
        "without_effect": {
            e.name: held_out(*_swapped(parts, theirs, -1, f"effect {e.name}")) for e, _v in parts
        },
    }
    for kind in ("map", "ripple", "function"):
        key = {"map": "without_map", "ripple": "without_periodic", "function": "function_from_"}[
            kind
        ]
        if kind == "function":
            key += dst
        out[key] = {names[j]: held_out(*_swapped(parts, theirs, j, kind)) for j in range(chain.nq)}
    out[f"{src}_held_out_pos_rms_mm"] = source.held_out(*_swapped(source.parts, {}, -1, ""))
    out[f"function_from_{dst}_on_{src}"] = {
        names[j]: source.held_out(*_swapped(source.parts, theirs, j, "function"))
        for j in range(chain.nq)
    }
    out[f"variance_inflation_{src}"] = dict(zip(names, source.inflation, strict=True))
    out[f"time_halves_{src}"] = source.halves
    return out


@dataclasses.dataclass
class _Session:
    """A saved model on one session as `--registration-only` carries it (the registration
    refitted on the session's training poses, the rest as saved), and a judge of variants of
    it on the session's held-out poses."""

    chain: Any
    data: Any
    position_only: bool
    carried: Any
    train_idx: np.ndarray
    val_idx: np.ndarray

    @classmethod
    def of(cls, work: Path, session: str, config: Any, chain: Any) -> _Session:
        """The model of `config` on `session`'s files in `work`."""
        from keo_service.fit.analysis import analyze, split_data
        from keo_service.io.analysis_report import saved_model
        from keo_service.offline.analyze import load_data

        files = work / session
        data, position_only = load_data(config, files / "encoder.csv", files / "tracker.csv")
        saved = saved_model(config, chain, position_only)
        carried = _quiet(analyze, chain.robot, data, position_only, saved)
        train_idx, val_idx = split_data(data)
        return cls(chain, data, position_only, carried, train_idx, val_idx)

    def __post_init__(self) -> None:
        self.model, self.x = self.carried.model, self.carried.x
        self.train, self.val = self.data.subset(self.train_idx), self.data.subset(self.val_idx)
        self.tau_tr = self.chain.gravity_torques(self.train.q)
        self.tau_va = self.chain.gravity_torques(self.val.q)
        self.noise = self.carried.report["registration"]["noise_estimate_mm"] * 1e-3
        self.width = 3 if self.position_only else 6

    def errors_mm(self, m: Any, z: np.ndarray) -> np.ndarray:
        """Each held-out pose's position error (mm) under model `m` with parameters `z`."""
        r = m.residuals(z, self.val, self.tau_va).reshape(-1, self.width)[:, :3]
        return np.asarray(np.linalg.norm(r, axis=1) * 1e3)

    def held_out(self, effects: list[Any], values: list[np.ndarray]) -> float:
        """The held-out RMS (mm) of the model made of `effects` with `values`, the
        registration refitted on the training poses with those terms held."""
        from keo_service.fit.model import Model, fit

        model = self.model
        z0 = np.concatenate([self.x[: model.n_reg], *values])
        m = Model(
            self.chain,
            self.position_only,
            effects,
            z0,
            {},
            model.temperature_ref,
            model.time_ref,
        )
        fixed = np.zeros(z0.size, dtype=bool)
        fixed[m.n_reg :] = True
        z = fit(m, self.train, self.tau_tr, z0, self.noise, fixed=fixed).x
        return float(np.sqrt(np.mean(self.errors_mm(m, z) ** 2)))


@dataclasses.dataclass
class _Source:
    """The model on its own session (registration refitted on its training poses, the rest as
    saved): its parts, a judge of variants on its held-out poses, its maps' variance
    inflation (fit.angle_maps.variance_inflation) on its training poses and its maps carried
    between the session's own halves in time (_time_halves)."""

    parts: list[Any]
    held_out: Any
    inflation: list[float | None]
    halves: dict[str, Any] | None


def _source_side(work: Path, src: str, config: Any, robot: Any) -> _Source:
    """What the source session's own data say: the model refitted there as
    `--registration-only` does, each variant judged on its held-out poses, and how much its
    poses let each joint's map be told from the others'."""
    from keo_service.core.chain import Chain
    from keo_service.fit.angle_maps import linearize, variance_inflation
    from keo_service.fit.effects import JointMaps
    from keo_service.fit.model import Model

    chain = Chain(robot)
    on_own = _Session.of(work, src, config, chain)
    model, x, position_only = on_own.model, on_own.x, on_own.position_only
    data, train, tau_tr = on_own.data, on_own.train, on_own.tau_tr
    train_idx, val_idx = on_own.train_idx, on_own.val_idx

    own_parts = list(model.parts(x))
    maps = model.find(JointMaps)
    inflation: list[float | None] = [None] * chain.nq
    halves = None
    if maps is not None:
        physical = [(e, v) for e, v in own_parts if not isinstance(e, JointMaps)]
        xp = np.concatenate([x[: model.n_reg], *[v for _e, v in physical]])
        before = Model(
            chain,
            position_only,
            [e for e, _v in physical],
            xp,
            {},
            model.temperature_ref,
            model.time_ref,
        )
        report = json.loads((work / src / "an" / "report.json").read_text())
        smoothing = next(e for e in report["effects"] if e["name"] == "joint_maps")["smoothing"]
        lin = linearize(before, xp, train, tau_tr)
        inflation = variance_inflation(lin, train.q, maps.knots, smoothing, xp.size)
        whole = linearize(before, xp, data, chain.gravity_torques(data.q))
        halves = _time_halves(
            whole,
            data,
            train_idx,
            val_idx,
            maps.knots,
            smoothing,
            model.n_reg,
            list(robot.joint_names),
        )
    return _Source(own_parts, on_own.held_out, inflation, halves)


def _time_halves(
    lin: Any,
    data: Any,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    knots: tuple[np.ndarray, ...],
    smoothing: float,
    n_reg: int,
    names: list[str],
) -> dict[str, Any]:
    """The session's maps fitted on the training poses of its first and of its second half in
    time (on the model before the maps, linearized in `lin`, the registration beside them, the
    analysis' knots and smoothing), each half's held-out poses judged with its own maps, with
    the other half's, and with its own but one joint's map from the other half (the
    registration refitted on that half's training poses each time): which joint's function
    does not carry from one stretch of the session to the next. The halves differ in their
    poses as well as in time (UR10 Series A: the same joint ranges, other configurations);
    where the timestamps are damaged (Series B) they are halves of the row order."""
    from keo_service.fit.angle_maps import _design, _penalty, _pos_rms_mm, _solve

    width = lin.r0.shape[1]
    n_other = lin.J.shape[1]
    design = _design(lin, data.q, knots)
    penalty = _penalty(n_other, knots)
    middle = float(np.median(data.t[train_idx]))
    fits = [train_idx[data.t[train_idx] <= middle], train_idx[data.t[train_idx] > middle]]
    judged = [val_idx[data.t[val_idx] <= middle], val_idx[data.t[val_idx] > middle]]
    steps = []
    for rows in fits:
        AtA, g = design.rows(rows, width).normal()
        steps.append(_solve(AtA, g, penalty.T @ penalty, smoothing))

    def held_out(half: int, maps: np.ndarray) -> float:
        fitted, test = design.rows(fits[half], width), design.rows(judged[half], width)
        registration = np.linalg.lstsq(
            fitted.J[:, :n_reg], -(fitted.r + fitted.B @ maps), rcond=None
        )[0]
        r = test.r + test.B @ maps + test.J[:, :n_reg] @ registration
        return _pos_rms_mm(r.reshape(-1, width))

    out: dict[str, Any] = {"hours": float(np.ptp(data.t) / 3600.0)}
    for half, label in ((0, "first"), (1, "second")):
        own, other = steps[half][n_other:], steps[1 - half][n_other:]
        swapped = {}
        start = 0
        for j, kn in enumerate(knots):
            trial = own.copy()
            trial[start : start + kn.size] = other[start : start + kn.size]
            start += kn.size
            if kn.size:
                swapped[names[j]] = held_out(half, trial)
        out[label] = {
            "held_out_poses": int(judged[half].size),
            "own_maps": held_out(half, own),
            "other_half_maps": held_out(half, other),
            "own_but_one_joint_from_the_other_half": swapped,
        }
    return out


def run(data_dir: Path, work: Path) -> dict[str, Any]:
    from keo_service.io.config import load_config
    from keo_service.io.importers import import_dataset
    from keo_service.offline.analyze import run_analysis

    config = load_config(CONFIG)
    own: dict[str, dict[str, Any]] = {}
    timings: dict[str, float] = {}
    for name, rel in SERIES.items():
        out = work / name
        if not (out / "tracker.csv").exists():
            import_dataset("ur10-lasertracker", data_dir / rel, out)
        start = time.perf_counter()
        own[name] = _quiet(
            run_analysis, config, out / "encoder.csv", out / "tracker.csv", out / "an", False
        )
        timings[f"fit {name}"] = time.perf_counter() - start
    rows = []
    for src, dst in (("A", "B"), ("B", "A")):
        model = load_config(work / src / "an" / "model.toml")
        start = time.perf_counter()
        rep = _quiet(
            run_analysis,
            model,
            work / dst / "encoder.csv",
            work / dst / "tracker.csv",
            work / f"{src}_on_{dst}",
            True,
        )
        timings[f"{src} on {dst}"] = time.perf_counter() - start
        rows.append(
            {
                "model_from": src,
                "applied_to": dst,
                "held_out_pos_rms_mm": rep["final"]["validation"]["pos_rms_mm"],
                "held_out_pos_max_mm": rep["final"]["validation"]["pos_max_mm"],
                "nominal_pos_rms_mm": rep["baseline"]["validation"]["pos_rms_mm"],
                "own_model_pos_rms_mm": own[dst]["final"]["validation"]["pos_rms_mm"],
                "carried_maps": rep.get("carried_maps"),
                "stated_accuracy": rep.get("predicted_vs_measured"),
            }
        )
    within = {k: v["final"]["validation"]["pos_rms_mm"] for k, v in own.items()}
    return {"transfer": rows, "within_session": within, "seconds": timings}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "ur10_lasertracker")
    ap.add_argument("--work", type=Path, default=None, help="keep the files here")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--decompose", action="store_true", help="what each carried figure is made of")
    args = ap.parse_args()
    with contextlib.ExitStack() as stack:
        work = args.work or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        result = run(args.data, work)
        if args.decompose:
            result["decomposition"] = [decompose(work, "A", "B"), decompose(work, "B", "A")]
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print("| model from | applied to | held out, mm RMS (max) | nominal there | own model |")
    print("|---|---|---|---|---|")
    for r in result["transfer"]:
        print(
            f"| {r['model_from']} | {r['applied_to']} | {r['held_out_pos_rms_mm']:.3f} "
            f"({r['held_out_pos_max_mm']:.2f}) | {r['nominal_pos_rms_mm']:.3f} | "
            f"{r['own_model_pos_rms_mm']:.3f} |"
        )
    print()
    print(
        "| model from | applied to | within the 95 % band: own session's band | with the "
        "between-session term | predicted / measured RMS, mm |"
    )
    print("|---|---|---|---|---|")
    for r in result["transfer"]:
        cov = r["stated_accuracy"] or {}
        if "within_session_band" not in cov:
            continue
        print(
            f"| {r['model_from']} | {r['applied_to']} | "
            f"{cov['within_session_band']['within_95_pct']:.1f} % | {cov['within_95_pct']:.1f} % "
            f"(+{cov['session_mm']:.3f} mm) | {cov['predicted_rms_mm']:.3f} / "
            f"{cov['measured_rms_mm']:.3f} |"
        )
    within = {k: round(v, 4) for k, v in result["within_session"].items()}
    print("within session, held out:", within)
    for dec in result.get("decomposition", []):
        _print_decomposition(dec)
    print("seconds:", {k: round(v, 1) for k, v in result["seconds"].items()}, file=sys.stderr)
    return 0


def _print_decomposition(dec: dict[str, Any]) -> None:
    print()
    print(
        f"{dec['model_from']}'s model on {dec['applied_to']}: held out "
        f"{dec['held_out_pos_rms_mm']:.4f} mm RMS"
    )
    for w in dec["where"]:
        print(f"  {w['where']}: {w['poses']} poses, {w['pos_rms_mm']:.4f} mm")
    print("  without:", {k: round(v, 4) for k, v in dec["without_effect"].items()})
    for key, label in (
        ("without_map", "without the map of"),
        ("without_periodic", "without the periodic terms of"),
        (f"function_from_{dec['applied_to']}", f"the joint's function from {dec['applied_to']}"),
    ):
        print(f"  {label}:", {k: round(v, 4) for k, v in dec[key].items()})
    src, dst = dec["model_from"], dec["applied_to"]
    print(
        f"  on {src}'s own held-out poses ({dec[f'{src}_held_out_pos_rms_mm']:.4f} mm as "
        f"saved), the joint's function from {dst}:",
        {k: round(v, 4) for k, v in dec[f"function_from_{dst}_on_{src}"].items()},
    )
    halves = dec.get(f"time_halves_{src}")
    if halves:
        print(f"  {src}'s maps fitted on each half of its {halves['hours']:.1f} h, held out:")
        for label in ("first", "second"):
            h = halves[label]
            print(
                f"    {label} half ({h['held_out_poses']} poses): own maps {h['own_maps']:.4f}, "
                f"the other half's {h['other_half_maps']:.4f}; own but one joint's from the "
                "other half:",
                {k: round(v, 4) for k, v in h["own_but_one_joint_from_the_other_half"].items()},
            )
    print(
        f"  {src}'s maps, variance inflation by the other joints' maps:",
        {
            k: None if v is None else round(v, 3)
            for k, v in dec[f"variance_inflation_{src}"].items()
        },
    )


if __name__ == "__main__":
    sys.exit(main())
