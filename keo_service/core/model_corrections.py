"""ModelCorrections to the nominal kinematic model that `keo analyze` identifies (data only)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Outside its calibrated angles a joint-angle map (and a coupling's map) fades linearly from
# its edge value to zero over a distance (rad): a table says nothing about angles it never
# saw, and holding its edge value there made a model carried to new angles worse than the
# nominal robot. `keo analyze` chooses the joint maps' distance per analysis on the held-out
# bands at the ends of each joint's range (fit.angle_maps.choose_taper) and writes it to
# model.toml (`[model] map_taper_rad`); this is the distance of a model file without that key
# and of the couplings' maps. About a quarter of the strain-wave ripple's period seen in the
# UR10 maps.
MAP_TAPER_RAD = 0.1


def taper_weight(q: np.ndarray, lo: float, hi: float, taper: float = MAP_TAPER_RAD) -> np.ndarray:
    """1 inside [lo, hi], falling linearly to 0 at `taper` rad outside, 0 beyond."""
    outside = np.maximum(lo - q, 0.0) + np.maximum(q - hi, 0.0)
    if taper <= 0:
        inside: np.ndarray = (outside == 0).astype(float)
        return inside
    out: np.ndarray = np.clip(1.0 - outside / taper, 0.0, 1.0)
    return out


def tapered_interp(
    q: np.ndarray, knots: np.ndarray, values: np.ndarray, taper: float = MAP_TAPER_RAD
) -> np.ndarray:
    """Linear interpolation between knots, the edge value fading to zero over `taper` rad
    outside them."""
    out: np.ndarray = np.interp(q, knots, values) * taper_weight(q, knots[0], knots[-1], taper)
    return out


@dataclass(frozen=True)
class ModelCorrections:
    nq: int
    joint_offsets: np.ndarray = field(default=None)  # type: ignore[arg-type]
    compliance: np.ndarray = field(default=None)  # type: ignore[arg-type]  # rad/(N m)
    backlash: np.ndarray = field(default=None)  # type: ignore[arg-type]  # rad, x direction
    cyclic: np.ndarray = field(default=None)  # type: ignore[arg-type]  # (nq, H, 2): a, b
    placement: np.ndarray = field(default=None)  # type: ignore[arg-type]  # (nq, 6)
    # joint-angle error maps: per joint (knots [rad], values [rad]), piecewise linear in the
    # joint's own angle, fading to zero over `map_taper` rad outside the knots; empty: no map
    maps: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    map_taper: float = MAP_TAPER_RAD
    # couplings across joints: (j, k, slope, knots, values): joint j's angle error moves with
    # joint k's angle, slope x (q_k - centre of the knots) + a piecewise-linear map of q_k
    couplings: tuple[tuple[int, int, float, np.ndarray, np.ndarray], ...] = ()
    # periodic joint errors (a strain-wave gear's kinematic error is periodic in the joint
    # angle): (joint, period rad, a, b): joint's angle error a sin(2 pi q / period) +
    # b cos(2 pi q / period); defined at every angle, so it extrapolates where a map cannot
    ripple: tuple[tuple[int, float, float, float], ...] = ()

    def __post_init__(self) -> None:
        zero = {
            "joint_offsets": (self.nq,),
            "compliance": (self.nq,),
            "backlash": (self.nq,),
            "cyclic": (self.nq, 2, 2),
            "placement": (self.nq, 6),
        }
        for name, shape in zero.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(shape))

    @property
    def is_zero(self) -> bool:
        if any(slope or np.any(v) for _j, _k, slope, _kn, v in self.couplings):
            return False
        if any(a or b for _j, _p, a, b in self.ripple):
            return False
        return not any(v.size and np.any(v) for _k, v in self.maps) and all(
            not np.any(getattr(self, n))
            for n in ("joint_offsets", "compliance", "backlash", "cyclic", "placement")
        )

    def map_ranges(self) -> list[tuple[float, float] | None]:
        """Each joint's calibrated range (first and last knot), None without a map."""
        out: list[tuple[float, float] | None] = [None] * self.nq
        for j, (knots, _values) in enumerate(self.maps):
            if knots.size:
                out[j] = (float(knots[0]), float(knots[-1]))
        return out

    def joint_angles(
        self, q: np.ndarray, tau: np.ndarray | None = None, direction: np.ndarray | None = None
    ) -> np.ndarray:
        """Effective joint angles for joints q (..., nq); tau: gravity torques (..., nq)."""
        q_eff: np.ndarray = q + self.joint_offsets
        if tau is not None and np.any(self.compliance):
            q_eff = q_eff + self.compliance * tau
        if direction is not None and np.any(self.backlash):
            q_eff = q_eff + self.backlash * direction
        if np.any(self.cyclic):
            for h in range(self.cyclic.shape[1]):
                k = h + 1
                q_eff = (
                    q_eff
                    + self.cyclic[:, h, 0] * np.sin(k * q)
                    + self.cyclic[:, h, 1] * np.cos(k * q)
                )
        if self.maps:
            q_eff = q_eff + self.map_error(q)
        if self.couplings:
            q_eff = q_eff + self.coupling_error(q)
        if self.ripple:
            q_eff = q_eff + self.ripple_error(q)
        return q_eff

    def ripple_error(self, q: np.ndarray) -> np.ndarray:
        """The periodic joint errors at joints q (..., nq)."""
        out = np.zeros(np.shape(q))
        for j, period, a, b in self.ripple:
            phase = 2 * np.pi * q[..., j] / period
            out[..., j] += a * np.sin(phase) + b * np.cos(phase)
        return out

    def coupling_error(self, q: np.ndarray) -> np.ndarray:
        """The couplings' angle error at joints q (..., nq): per coupling, on joint j, the
        slope times joint k's angle from the knots' centre plus the map of joint k's angle
        (fading to zero beyond the knots, as the maps)."""
        out = np.zeros(np.shape(q))
        for j, k, slope, knots, values in self.couplings:
            qk = q[..., k]
            centre = 0.5 * (knots[0] + knots[-1]) if knots.size else 0.0
            out[..., j] += slope * (qk - centre)
            if knots.size:
                out[..., j] += tapered_interp(qk, knots, values)
        return out

    def map_error(self, q: np.ndarray) -> np.ndarray:
        """The maps' angle error at joints q (..., nq): linear between knots, fading to zero
        over `map_taper` rad beyond them (never extrapolated, never held). Each joint's map on
        its own: a pose outside one joint's range keeps the other joints' maps."""
        out = np.zeros(np.shape(q))
        for j, (knots, values) in enumerate(self.maps):
            if knots.size:
                out[..., j] = tapered_interp(q[..., j], knots, values, self.map_taper)
        return out


def approach_directions(q: np.ndarray) -> np.ndarray:
    """For stop-and-measure data in time order: the sign of each joint's last move (a joint
    that did not move keeps the direction it had)."""
    d = np.zeros_like(q)
    d[1:] = np.sign(np.diff(q, axis=0))
    return persist_directions(d)


def persist_directions(direction: np.ndarray) -> np.ndarray:
    """A joint that does not move keeps the direction of its last move (its backlash side)."""
    direction = np.asarray(direction)
    if direction.shape[0] == 0:
        return direction.copy()
    # forward fill per joint: each row takes the newest row at or before it that moved
    rows = np.arange(direction.shape[0])[:, None]
    newest = np.maximum.accumulate(np.where(direction != 0, rows, 0), axis=0)
    out: np.ndarray = np.take_along_axis(direction, newest, axis=0)
    return out
