"""Local obstacle map around the vehicle (paper 000 section V): a particle filter in the frame H.

* **Cells** discretise the space around the vehicle by azimuth and zenith distance (``az_bins`` x
  ``zen_bins``). A measured obstacle point overwrites its cell: every particle there is removed and
  ``copies`` particles are placed at the point (reactive behaviour, particles for the spread).
* **Free-space carving** (added to the paper's rule so that an obstacle that moved away is forgotten):
  a particle inside the camera's view whose sector saw something farther, or nothing within range, is
  removed.
* **Time update**, eq. (14), per particle j with its own noise samples::

      p_j <- Rz(psi_j)^T (p_j - u_j),  u_j = dT (v_k + v_k+1 + n_v,j) / 2,
      psi_j = dT (psidot_k + psidot_k+1 + n_psi,j) / 2

  (the paper prints ``v_k+1 - v_k``; the trapezoidal *sum* is what makes ``u`` a displacement).
* **Ageing and removal**: particles older than ``max_age_s`` or farther than ``radius_m`` are dropped.
* **Sector summary** like MAVLink ``OBSTACLE_DISTANCE``: 72 sectors of 5° about the z axis of H (sector 0
  centred on the heading, clockwise positive as NED yaw), the nearest horizontal distance of the
  particles within ``z_band_m`` of the vehicle; ``inf`` where the sector was observed within
  ``max_age_s`` and holds nothing (free), ``nan`` where it never was or the observation expired.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perception.obstacles import SectorObservation


@dataclass(frozen=True)
class ObstacleMapConfig:
    az_bins: int = 72                 # cells in azimuth (5°)
    zen_bins: int = 36                # cells in zenith distance (5°)
    copies: int = 5                   # particles per measured point
    max_particles: int = 20000
    radius_m: float = 5.0             # particles farther than this are dropped
    max_age_s: float = 8.0            # ... and older than this
    velocity_noise_m_s: float = 0.05  # std of n_v per axis (eq. 14)
    yaw_rate_noise_rad_s: float = 0.02  # std of n_psi (eq. 14)
    carve_margin_m: float = 0.15      # a particle this much in front of the measured surface is free space
    sectors: int = 72                 # OBSTACLE_DISTANCE-style summary
    z_band_m: float = 1.0             # particles within this height of the vehicle count for the summary
    min_distance_m: float = 0.3
    max_distance_m: float = 3.5


@dataclass(frozen=True)
class ObstacleSectors:
    """OBSTACLE_DISTANCE-like summary in H: sector i is centred at azimuth ``angle_offset_deg + i*increment``."""

    stamp_s: float
    distances_m: NDArray[np.float64]   # (sectors,), np.inf = free, np.nan = unknown
    increment_deg: float
    angle_offset_deg: float
    min_distance_m: float
    max_distance_m: float
    frame: str = "H"


class ObstacleMap:
    """Particles in H; call :meth:`predict` with the motion between frames, then :meth:`measure`."""

    def __init__(self, config: ObstacleMapConfig | None = None) -> None:
        self.config = config or ObstacleMapConfig()
        self.points_h_m = np.zeros((0, 3))
        self.ages_s = np.zeros(0)
        self._yaw_total_rad = 0.0                                  # integral of the yaw updates
        self._observed_s = np.full(self.config.sectors, -np.inf)  # per world-azimuth sector
        self._last_stamp: float | None = None

    def __len__(self) -> int:
        return int(self.points_h_m.shape[0])

    def cells_of(self, points_h_m: NDArray[np.float64]) -> NDArray[np.intp]:
        """Cell index (azimuth-major) of points in H."""
        cfg = self.config
        x, y, z = points_h_m[:, 0], points_h_m[:, 1], points_h_m[:, 2]
        az = np.arctan2(y, x)                                  # [-pi, pi]
        zen = np.arctan2(np.hypot(x, y), -z)                   # zenith distance from "up" (-z in NED), [0, pi]
        ia = np.minimum((az + math.pi) * (cfg.az_bins / (2 * math.pi)), cfg.az_bins - 1).astype(np.intp)
        iz = np.minimum(zen * (cfg.zen_bins / math.pi), cfg.zen_bins - 1).astype(np.intp)
        return ia * cfg.zen_bins + iz

    def predict(self, dt_s: float, v_h_k: NDArray[np.float64], v_h_k1: NDArray[np.float64], yaw_rate_k: float,
                yaw_rate_k1: float, rng: np.random.Generator) -> None:
        """Time update, eq. (14), then ageing and removal."""
        cfg = self.config
        if dt_s <= 0.0:
            return
        n = len(self)
        self._yaw_total_rad += dt_s * (yaw_rate_k + yaw_rate_k1) / 2.0
        if n:
            n_v = rng.normal(0.0, cfg.velocity_noise_m_s, size=(n, 3))
            n_psi = rng.normal(0.0, cfg.yaw_rate_noise_rad_s, size=n)
            u = dt_s * (np.asarray(v_h_k) + np.asarray(v_h_k1) + n_v) / 2.0           # eq. (14)
            psi = dt_s * (yaw_rate_k + yaw_rate_k1 + n_psi) / 2.0
            d = self.points_h_m - u
            c, s = np.cos(psi), np.sin(psi)
            # Rz(psi)^T d
            self.points_h_m = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
            self.ages_s = self.ages_s + dt_s
        self._prune()

    def _prune(self) -> None:
        cfg = self.config
        keep = (self.ages_s <= cfg.max_age_s) & (np.einsum("ij,ij->i", self.points_h_m, self.points_h_m)
                                                   <= cfg.radius_m**2)
        if not keep.all():
            self.points_h_m = self.points_h_m[keep]
            self.ages_s = self.ages_s[keep]

    def measure(self, stamp_s: float, obs: SectorObservation) -> None:
        """Measurement step: carve free space, overwrite the measured cells, record observed sectors."""
        cfg = self.config
        self._last_stamp = stamp_s
        if len(self):
            sec = obs.sector_of_points_h(self.points_h_m)
            inview = sec >= 0
            if inview.any():
                rng_meas = obs.ranges_m[np.where(inview, sec, 0)]
                rng_p = np.linalg.norm(self.points_h_m - obs.p_hc_m, axis=1)
                free = inview & ~np.isnan(rng_meas) & (rng_p < rng_meas - cfg.carve_margin_m)
                if free.any():
                    self.points_h_m = self.points_h_m[~free]
                    self.ages_s = self.ages_s[~free]
        pts = obs.points_h_m
        if pts.shape[0]:
            cells = self.cells_of(pts)
            if len(self):
                measured = np.zeros(cfg.az_bins * cfg.zen_bins, dtype=bool)
                measured[cells] = True
                drop = measured[self.cells_of(self.points_h_m)]
                self.points_h_m = self.points_h_m[~drop]
                self.ages_s = self.ages_s[~drop]
            new = np.repeat(pts, cfg.copies, axis=0)
            self.points_h_m = np.concatenate([self.points_h_m, new])
            self.ages_s = np.concatenate([self.ages_s, np.zeros(new.shape[0])])
            if len(self) > cfg.max_particles:  # oldest go first
                order = np.argsort(self.ages_s, kind="stable")[: cfg.max_particles]
                self.points_h_m = self.points_h_m[order]
                self.ages_s = self.ages_s[order]
        # sectors seen by this frame (a point or free space), kept in world azimuth
        seen = ~np.isnan(obs.ranges_m)
        if seen.any():
            rays = obs.rays_h[seen]
            horiz = np.hypot(rays[:, 0], rays[:, 1]) > 0.05
            az = np.arctan2(rays[horiz, 1], rays[horiz, 0]) + self._yaw_total_rad
            self._observed_s[self._sector_index(az)] = stamp_s
            # the camera's sectors are wider than 5°: mark the azimuth span between neighbouring rays too
            if az.size >= 2:
                lo, hi = self._span(az)
                fine = np.linspace(lo, hi, max(2, int((hi - lo) / math.radians(2.5)) + 1))
                self._observed_s[self._sector_index(fine)] = stamp_s

    @staticmethod
    def _span(az: NDArray[np.float64]) -> tuple[float, float]:
        centre = math.atan2(float(np.mean(np.sin(az))), float(np.mean(np.cos(az))))
        rel = (az - centre + math.pi) % (2 * math.pi) - math.pi
        return centre + float(rel.min()), centre + float(rel.max())

    def _sector_index(self, az_rad: NDArray[np.floating[Any]]) -> NDArray[np.intp]:
        n = self.config.sectors
        inc = 2 * math.pi / n
        return (np.floor((az_rad + inc / 2) / inc).astype(np.intp)) % n

    def sectors(self, stamp_s: float) -> ObstacleSectors:
        cfg = self.config
        n = cfg.sectors
        # observed flags, from world azimuth back to H (rotate by the accumulated yaw)
        shift = self._yaw_total_rad
        centres_h = np.arange(n) * (2 * math.pi / n)
        obs_age = stamp_s - self._observed_s[self._sector_index(centres_h + shift)]
        dist = np.where(obs_age <= cfg.max_age_s, np.inf, np.nan)
        if len(self):
            p = self.points_h_m
            band = np.abs(p[:, 2]) <= cfg.z_band_m
            if band.any():
                q = p[band]
                d = np.hypot(q[:, 0], q[:, 1])
                idx = self._sector_index(np.arctan2(q[:, 1], q[:, 0]))
                best = np.full(n, np.inf)
                np.minimum.at(best, idx, d)
                has = np.isfinite(best)
                dist[has] = np.clip(best[has], cfg.min_distance_m, None)
        return ObstacleSectors(stamp_s, dist, 360.0 / n, 0.0, cfg.min_distance_m, cfg.max_distance_m)

    def nearest_h(self) -> NDArray[np.float64] | None:
        if not len(self):
            return None
        i = int(np.argmin(np.einsum("ij,ij->i", self.points_h_m, self.points_h_m)))
        return self.points_h_m[i].copy()
