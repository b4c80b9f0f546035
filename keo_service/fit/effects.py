"""The effects `keo analyze` can add to the nominal model: one class per effect, all behind the
`Effect` protocol (fit.model: what the model needs of an effect). An effect knows its
parameter count, how its values change the joints (through `ModelCorrections`) or the sensor's
position, how its numbers read (records with joint, parameter and unit), whether the fit
reduces it to the directions the data identifies, and how it is written to and read from the
config's [model] section. Nothing outside this module compares an effect's name: a new effect
is a new class and an entry in EFFECTS. No I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from keo_service.core.model_corrections import MAP_TAPER_RAD, ModelCorrections
from keo_service.fit.model import Data, Effect, Model


def _set(corr: ModelCorrections, **kw: np.ndarray) -> ModelCorrections:
    fields: dict[str, Any] = kw
    return dataclasses.replace(corr, **fields)


@dataclass(frozen=True)
class _PerJoint:
    """An effect with the same few numbers for every joint, applied through ModelCorrections."""

    name: ClassVar[str]
    description: ClassVar[str]
    labels: ClassVar[tuple[tuple[str, str], ...]]  # (parameter, unit) per joint, in order
    config_key: ClassVar[str]
    reduce: ClassVar[bool] = True

    def size(self, nq: int) -> int:
        return nq * len(self.labels)

    def usable(self, data: Data) -> bool:
        return True

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        raise NotImplementedError

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        return None

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        out = []
        for i, (v, s) in enumerate(zip(values, se, strict=True)):
            j, k = divmod(i, len(self.labels))
            parameter, unit = self.labels[k]
            joint = joint_names[j] if j < len(joint_names) else f"joint_{j + 1}"
            out.append(
                {
                    "joint": joint,
                    "parameter": parameter,
                    "unit": unit,
                    "value": float(v),
                    "se": float(s),
                }
            )
        return out

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        return {self.config_key: np.asarray(values, dtype=float).reshape(-1).tolist()}

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        return self, np.asarray(section[self.config_key], dtype=float)


@dataclass(frozen=True)
class JointOffsets(_PerJoint):
    name: ClassVar[str] = "joint_offsets"
    description: ClassVar[str] = "zero offset of each joint (rad)"
    labels: ClassVar[tuple[tuple[str, str], ...]] = (("zero offset", "rad"),)
    config_key: ClassVar[str] = "joint_offsets"

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return _set(corr, joint_offsets=corr.joint_offsets + values)


@dataclass(frozen=True)
class Geometry(_PerJoint):
    name: ClassVar[str] = "geometry"
    description: ClassVar[str] = "joint placement errors, identifiable combinations only (m, rad)"
    labels: ClassVar[tuple[tuple[str, str], ...]] = (
        ("link x", "m"),
        ("link y", "m"),
        ("link z", "m"),
        ("link rx", "rad"),
        ("link ry", "rad"),
        ("link rz", "rad"),
    )
    config_key: ClassVar[str] = "placement"

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return _set(corr, placement=corr.placement + values.reshape(-1, 6))


@dataclass(frozen=True)
class Compliance(_PerJoint):
    name: ClassVar[str] = "compliance"
    description: ClassVar[str] = "joint deflection per gravity torque (rad/(N m))"
    labels: ClassVar[tuple[tuple[str, str], ...]] = (("compliance", "rad/(N m)"),)
    config_key: ClassVar[str] = "compliance"

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return _set(corr, compliance=corr.compliance + values)


@dataclass(frozen=True)
class Backlash(_PerJoint):
    name: ClassVar[str] = "backlash"
    description: ClassVar[str] = "joint offset that follows the direction of the last move (rad)"
    labels: ClassVar[tuple[tuple[str, str], ...]] = (("backlash", "rad"),)
    config_key: ClassVar[str] = "backlash"

    def usable(self, data: Data) -> bool:
        return data.direction is not None

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return _set(corr, backlash=corr.backlash + values)


@dataclass(frozen=True)
class Cyclic(_PerJoint):
    name: ClassVar[str] = "cyclic"
    description: ClassVar[str] = "1st and 2nd harmonics of each joint angle (rad)"
    labels: ClassVar[tuple[tuple[str, str], ...]] = (
        ("1st harmonic sin", "rad"),
        ("1st harmonic cos", "rad"),
        ("2nd harmonic sin", "rad"),
        ("2nd harmonic cos", "rad"),
    )
    config_key: ClassVar[str] = "cyclic"

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return _set(corr, cyclic=corr.cyclic + values.reshape(-1, 2, 2))


@dataclass(frozen=True)
class _SensorDrift:
    """A drift of the sensor's position along one variable of the data: three numbers
    (x, y, z per unit of the variable), about the model's reference value of it."""

    name: ClassVar[str]
    description: ClassVar[str]
    unit: ClassVar[str]
    config_key: ClassVar[str]
    reduce: ClassVar[bool] = False

    def size(self, nq: int) -> int:
        return 3

    def usable(self, data: Data) -> bool:
        return True

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return corr

    def variable(self, data: Data, model: Model) -> np.ndarray:
        raise NotImplementedError

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        offset: np.ndarray = np.outer(self.variable(data, model), values)
        return offset

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        return [
            {
                "joint": "sensor",
                "parameter": f"drift {axis}",
                "unit": self.unit,
                "value": float(v),
                "se": float(s),
            }
            for axis, v, s in zip("xyz", values, se, strict=True)
        ]

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        return {self.config_key: np.asarray(values, dtype=float).tolist()}

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        return self, np.asarray(section[self.config_key], dtype=float)


@dataclass(frozen=True)
class Temperature(_SensorDrift):
    name: ClassVar[str] = "temperature"
    description: ClassVar[str] = "sensor position drift per degree C (m/C)"
    unit: ClassVar[str] = "m/C"
    config_key: ClassVar[str] = "temperature_m_per_c"
    column: ClassVar[str] = "temperature_c"  # the tracker file's extra column

    def usable(self, data: Data) -> bool:
        return self.column in data.extra

    @classmethod
    def reference(cls, data: Data) -> float:
        """The data's mean temperature (0 without the column): the drift is about it."""
        return float(np.mean(data.extra[cls.column])) if cls.column in data.extra else 0.0

    def variable(self, data: Data, model: Model) -> np.ndarray:
        out: np.ndarray = data.extra[self.column] - model.temperature_ref
        return out


@dataclass(frozen=True)
class TimeDrift(_SensorDrift):
    name: ClassVar[str] = "time_drift"
    description: ClassVar[str] = "sensor position drift per second (m/s)"
    unit: ClassVar[str] = "m/s"
    config_key: ClassVar[str] = "time_drift_m_per_s"

    @classmethod
    def reference(cls, data: Data) -> float:
        """The data's mean time: the drift is about it."""
        return float(np.mean(data.t))

    def variable(self, data: Data, model: Model) -> np.ndarray:
        out: np.ndarray = data.t - model.time_ref
        return out


def split_maps(
    knots: tuple[np.ndarray, ...], values: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """A flat vector of map values as (knots, values) per joint."""
    out, k = [], 0
    for kn in knots:
        out.append((kn, values[k : k + kn.size]))
        k += kn.size
    return tuple(out)


@dataclass(frozen=True, eq=False)
class JointMaps:
    """Joint-angle error maps (fit.angle_maps): each joint's angle error as a piecewise-
    linear function of its own angle on `knots` (rad; empty: no map for that joint). The
    knots depend on the data, so the maps are fitted by their own linear solve and tried
    after the other effects."""

    knots: tuple[np.ndarray, ...] = ()
    # the fade to zero outside the knots (rad; fit.angle_maps.choose_taper)
    taper: float = MAP_TAPER_RAD
    name: ClassVar[str] = "joint_maps"
    description: ClassVar[str] = (
        "joint-angle error maps: angle error vs the joint's own angle (rad)"
    )
    reduce: ClassVar[bool] = False

    def size(self, nq: int) -> int:
        return sum(k.size for k in self.knots)

    def usable(self, data: Data) -> bool:
        return True

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return dataclasses.replace(corr, maps=split_maps(self.knots, values), map_taper=self.taper)

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        return None

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        """Each joint's map: knots, values and standard errors (rad), its range."""
        out = []
        k = 0
        for j, kn in enumerate(self.knots):
            if not kn.size:
                continue
            v, s = values[k : k + kn.size], se[k : k + kn.size]
            k += kn.size
            out.append(
                {
                    "joint": joint_names[j] if j < len(joint_names) else f"joint_{j + 1}",
                    "parameter": "angle error map",
                    "unit": "rad",
                    "knots": kn.tolist(),
                    "values": v.tolist(),
                    "se": s.tolist(),
                    "range_rad": [float(kn[0]), float(kn[-1])],
                    "peak_mrad": float(np.max(np.abs(v)) * 1e3),
                }
            )
        return out

    def ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """Per joint the first and last knot (-inf, +inf without a map)."""
        lo = np.array([kn[0] if kn.size else -np.inf for kn in self.knots])
        hi = np.array([kn[-1] if kn.size else np.inf for kn in self.knots])
        return lo, hi

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        maps = split_maps(self.knots, values)
        return {
            "map_knots": [k.tolist() for k, _v in maps],
            "map_values": [v.tolist() for _k, v in maps],
            "map_taper_rad": self.taper,
        }

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        knots = tuple(np.asarray(k, dtype=float) for k in section["map_knots"])
        values = [v for joint in section["map_values"] for v in joint]
        taper = float(section.get("map_taper_rad", MAP_TAPER_RAD))
        return JointMaps(knots, taper), np.asarray(values, dtype=float)


@dataclass(frozen=True, eq=False)
class Couplings:
    """Effects across joints (fit.coupling): joint j's angle error as a smooth function of
    joint k's angle, a linear term (about the centre of the knots) and a piecewise-linear map
    on knots of q_k. `pairs`: per coupling (j, k, knots); values per coupling: the slope
    (rad/rad), then the map's values (rad)."""

    pairs: tuple[tuple[int, int, np.ndarray], ...] = ()
    name: ClassVar[str] = "couplings"
    description: ClassVar[str] = (
        "couplings across joints: a joint's angle error vs another joint's angle (rad)"
    )
    reduce: ClassVar[bool] = False

    def size(self, nq: int) -> int:
        return sum(1 + kn.size for _j, _k, kn in self.pairs)

    def usable(self, data: Data) -> bool:
        return True

    def split(self, values: np.ndarray) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
        out, i = [], 0
        for j, k, kn in self.pairs:
            out.append((j, k, float(values[i]), kn, values[i + 1 : i + 1 + kn.size]))
            i += 1 + kn.size
        return out

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        return dataclasses.replace(corr, couplings=tuple(self.split(values)))

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        return None

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        """Per coupling: the slope with its standard error and the map, and a sentence."""

        def name(j: int) -> str:
            return joint_names[j] if j < len(joint_names) else f"joint_{j + 1}"

        out = []
        for (j, k, slope, kn, v), (_j, _k, slope_se, _kn, v_se) in zip(
            self.split(values), self.split(se), strict=True
        ):
            peak = float(np.max(np.abs(v)) * 1e3) if v.size else 0.0
            text = (
                f"{name(j)}'s angle moves with {name(k)}: {slope * 1e3:+.3f} mrad per rad "
                f"(+/- {slope_se * 1e3:.3f})"
            )
            if v.size:
                text += f", and a map of {name(k)}'s angle peaking at {peak:.3f} mrad"
            out.append(
                {
                    "joint": name(j),
                    "parameter": f"angle error per rad of {name(k)}",
                    "unit": "rad/rad",
                    "value": slope,
                    "se": slope_se,
                    "with": name(k),
                    "knots": kn.tolist(),
                    "values": v.tolist(),
                    "values_se": v_se.tolist(),
                    "peak_mrad": peak,
                    "text": text,
                }
            )
        return out

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        parts = self.split(values)
        return {
            "coupling_joints": [[j, k] for j, k, _s, _kn, _v in parts],
            "coupling_slopes": [s for _j, _k, s, _kn, _v in parts],
            "coupling_knots": [kn.tolist() for _j, _k, _s, kn, _v in parts],
            "coupling_values": [v.tolist() for _j, _k, _s, _kn, v in parts],
        }

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        pairs, values = [], []
        for (j, k), slope, kn, v in zip(
            section["coupling_joints"],
            section["coupling_slopes"],
            section["coupling_knots"],
            section["coupling_values"],
            strict=True,
        ):
            pairs.append((int(j), int(k), np.asarray(kn, dtype=float)))
            values += [float(slope), *[float(x) for x in v]]
        return Couplings(tuple(pairs)), np.asarray(values, dtype=float)


@dataclass(frozen=True, eq=False)
class JointRipple:
    """Periodic joint errors: per term a joint and a period (rad of that joint's angle), the
    joint's angle error a sin(2 pi q / period) + b cos(2 pi q / period). A strain-wave gear's
    kinematic error is periodic in the joint angle, so unlike a map this extrapolates. The
    terms (joints and periods) come from the data: `prepare` reads them off each joint's
    periodogram of the residual (fit.ripple); values per term: a, b (rad)."""

    terms: tuple[tuple[int, float], ...] = ()
    name: ClassVar[str] = "joint_ripple"
    description: ClassVar[str] = (
        "periodic joint error (strain-wave gear ripple): sine and cosine of each joint's angle "
        "at the periods its residual's spectrum shows (rad)"
    )
    reduce: ClassVar[bool] = True

    def size(self, nq: int) -> int:
        return 2 * len(self.terms)

    def usable(self, data: Data) -> bool:
        return True

    def prepare(
        self, model: Model, x: np.ndarray, data: Data, tau: np.ndarray, noise: float
    ) -> tuple[JointRipple, dict[str, Any]]:
        """The terms the residual's spectra show (fit.ripple), and the spectra."""
        from keo_service.fit.ripple import find_terms

        terms, spectra = find_terms(model, x, data, tau, noise)
        return JointRipple(tuple(terms)), spectra

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        ripple = tuple(
            (j, p, float(values[2 * i]), float(values[2 * i + 1]))
            for i, (j, p) in enumerate(self.terms)
        )
        return dataclasses.replace(corr, ripple=corr.ripple + ripple)

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        return None

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        out = []
        for i, (j, period) in enumerate(self.terms):
            joint = joint_names[j] if j < len(joint_names) else f"joint_{j + 1}"
            for k, part in enumerate(("sin", "cos")):
                out.append(
                    {
                        "joint": joint,
                        "parameter": f"ripple {part}, period {period:.4f} rad",
                        "unit": "rad",
                        "value": float(values[2 * i + k]),
                        "se": float(se[2 * i + k]),
                        "period_rad": float(period),
                        "per_revolution": float(2 * np.pi / period),
                    }
                )
        return out

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        return {
            "ripple_joints": [j for j, _p in self.terms],
            "ripple_periods_rad": [p for _j, p in self.terms],
            "ripple_sin": [float(v) for v in values[0::2]],
            "ripple_cos": [float(v) for v in values[1::2]],
        }

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        terms = tuple(
            (int(j), float(p))
            for j, p in zip(section["ripple_joints"], section["ripple_periods_rad"], strict=True)
        )
        values = np.column_stack(
            [np.asarray(section["ripple_sin"], float), np.asarray(section["ripple_cos"], float)]
        ).ravel()
        return JointRipple(terms), values


# every effect by its name; the analysis tries CANDIDATES in this order, then the maps
EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        JointOffsets(),
        Geometry(),
        Compliance(),
        Backlash(),
        Cyclic(),
        Temperature(),
        TimeDrift(),
        JointMaps(),
        Couplings(),
        JointRipple(),
    )
}
CANDIDATES = (
    "joint_offsets",
    "geometry",
    "compliance",
    "backlash",
    "cyclic",
    "temperature",
    "time_drift",
    "joint_ripple",
)
MAPS = JointMaps.name


def effect_from_config(name: str, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
    """A saved effect (model.effects entry) and its values; KeyError for an unknown name."""
    return EFFECTS[name].from_config(section)


def config_fields(model: Model, x: np.ndarray) -> dict[str, Any]:
    """The [model] keys of every effect in `model` (values in their own parameters)."""
    out: dict[str, Any] = {"effects": model.names}
    for effect, values in model.parts(x):
        out.update(effect.to_config(values, model.chain.nq))
    return out
