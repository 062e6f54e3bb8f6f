"""Local obstacle map around the vehicle (paper 000 section V): a particle filter in the frame H.

* **Cells** discretise the space around the vehicle by azimuth and zenith distance (``az_bins`` x
  ``zen_bins``). A measured obstacle point overwrites its cell: every particle there is removed and
  ``copies`` particles are placed at the point (reactive behaviour, particles for the spread) — except
  particles nearer the camera than its minimum range, which it cannot see.
* **Free-space carving** (added to the paper's rule so that an obstacle that moved away is forgotten;
  never nearer the camera than its minimum range plus ``carve_blind_margin_m``, where it is blind or a
  sector's reading comes from the pixels beyond the blind part):
  a particle inside the camera's view whose sector saw something farther, or nothing within range, is
  removed.
* **Time update**, eq. (14), per particle j with its own noise samples::

      p_j <- Rz(psi_j)^T (p_j - u_j),  u_j = dT (v_k + v_k+1 + n_v,j) / 2,
      psi_j = dT (psidot_k + psidot_k+1 + n_psi,j) / 2

  (the paper prints ``v_k+1 - v_k``; the trapezoidal *sum* is what makes ``u`` a displacement).
* **Ageing and removal**: particles older than ``max_age_s`` or farther than ``radius_m`` are dropped —
  except that within ``near_field_m`` (horizontally) of the vehicle they live ``near_field_max_age_s``. The
  camera looks 45 deg right and down: a wall the vehicle slides along on its left, or one it is too close to
  see (the minimum range), is not seen again however long the vehicle stays beside it, and forgetting it
  after ``max_age_s`` let a pushed vehicle close to 0.30 m of it (issue 14, the corner push: the wall ahead
  had been seen 8 s before, from 1 m east). The near field reaches past the repulsion's influence distance by
  what the vehicle may drift toward a surface it no longer sees while the memory lasts: with only the
  influence distance, a wall seen from 1.2-1.7 m went at 8 s while still 1.0-1.2 m away, the vehicle, turning
  to the column, drifted to 0.89 m of it, and the map's nearest point was a later sighting 0.5 m along the
  wall, 8-18 cm farther than the wall (issue 29, the fresh-clone demo). What the camera does see again still
  replaces it (carving and overwriting), and a held particle that leaves the near field goes at once if it is
  older than ``max_age_s``.
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
    near_field_m: float = 1.5         # ... but within this horizontal distance of the vehicle only older than
    near_field_max_age_s: float = 20.0  # this: the repulsion's influence distance (0.9 m) plus what a vehicle
                                        # holding still drifts in the 12 s more (0.6 m at 0.05 m/s; issue 29)
    velocity_noise_m_s: float = 0.1   # std of n_v per axis (eq. 14): white per frame, so that the spread after 1 s
                                      # matches the drift of a 0.02 m/s velocity error that persists that long
    yaw_rate_noise_rad_s: float = 0.02  # std of n_psi (eq. 14)
    carve_margin_m: float = 0.15      # a particle this much in front of the measured surface is free space
    carve_blind_margin_m: float = 0.3  # ... but not within this distance beyond the sensor's minimum range:
                                       # a surface nearer than the minimum range gives no reading, so a sector
                                       # that straddles it reports a farther surface (its closest *valid* pixel)
    measurement_noise_per_m: float = 0.02  # std of a measured point's position per metre of distance (depth
                                           # noise and ~1 deg of attitude error): the copies are drawn from it
    sectors: int = 72                 # OBSTACLE_DISTANCE-style summary
    z_band_m: float = 1.0             # particles within this height of the vehicle count for the summary
    floor_margin_m: float = 0.15      # ... but not those this close above the floor (when its height is known):
                                      # the floor the camera saw is no obstacle, and a sector known only by it
                                      # is not a sector the camera has looked at (a script backed 0.4 m into
                                      # the blind side over floor points, CI's MAVSDK flight at 1.05 m height)
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


def sector_index(az_rad: NDArray[np.floating[Any]], sectors: int, angle_offset_rad: float = 0.0) -> NDArray[np.intp]:
    """The sector of each azimuth (H) when sector i of ``sectors`` is centred at ``angle_offset_rad + i * 2 pi /
    sectors``, as OBSTACLE_DISTANCE numbers them."""
    inc = 2 * math.pi / sectors
    return (np.floor((az_rad - angle_offset_rad) / inc + 0.5).astype(np.intp)) % sectors


_NAN = np.array([np.nan])   # appended to the sector ranges: what sector -1 (out of view) reads


class ObstacleMap:
    """Particles in H; call :meth:`predict` with the motion between frames, then :meth:`measure`.

    ``points_h_m`` (N×3) and ``ages_s`` are replaced at every update, never modified in place, so an array
    handed out (e.g. in a pipeline output) stays a snapshot of the map at that frame.
    """

    def __init__(self, config: ObstacleMapConfig | None = None) -> None:
        self.config = config or ObstacleMapConfig()
        self._p = np.zeros((3, 0))      # particles one row per axis: the per-axis math runs on contiguous rows
        self.ages_s = np.zeros(0)
        # per particle: no ray passed over the point it samples (perception.obstacles.top_seen_over): a surface
        # that may reach higher than the camera saw, as a wall seen from below does; the objects inferred from
        # the floor they hide (perception.hidden_floor) too, their height is unknown
        self.open_top = np.zeros(0, dtype=bool)
        self._yaw_total_rad = 0.0                                  # integral of the yaw updates
        self._observed_s = np.full(self.config.sectors, -np.inf)  # per world-azimuth sector
        self._last_stamp: float | None = None
        # azimuth and horizontal distance of the particles, computed once per frame for the cells and the
        # summary; valid while ``_p`` is the array they were computed for
        self._polar: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = None

    @property
    def points_h_m(self) -> NDArray[np.float64]:
        """The particles in H, N×3 (a view of the map's arrays; the map replaces them, never writes them)."""
        return self._p.T

    @points_h_m.setter
    def points_h_m(self, points_h_m: NDArray[np.float64]) -> None:
        self._p = np.array(np.asarray(points_h_m, dtype=float).reshape(-1, 3).T, order="C")
        self.open_top = np.zeros(self._p.shape[1], dtype=bool)
        self._polar = None

    def __len__(self) -> int:
        return int(self._p.shape[1])

    def _polar_of_particles(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = self._p
        if self._polar is None or self._polar[0] is not p:
            az, horiz = _polar(p[0], p[1])
            self._polar = (p, az, horiz)
        return self._polar[1], self._polar[2]

    def _set_particles(self, p: NDArray[np.float64], ages_s: NDArray[np.float64], open_top: NDArray[np.bool_],
                       az: NDArray[np.float64] | None = None, horiz: NDArray[np.float64] | None = None) -> None:
        self._p, self.ages_s, self.open_top = p, ages_s, open_top
        self._polar = None if az is None or horiz is None else (p, az, horiz)

    def cells_of(self, points_h_m: NDArray[np.float64]) -> NDArray[np.intp]:
        """Cell index (azimuth-major) of points in H."""
        az, horiz = _polar(points_h_m[:, 0], points_h_m[:, 1])
        return self._azimuth_cells(az) * self.config.zen_bins + self._zenith_cells(horiz, points_h_m[:, 2])

    def _azimuth_cells(self, az: NDArray[np.float64]) -> NDArray[np.intp]:
        n = self.config.az_bins
        return np.minimum((az + math.pi) * (n / (2 * math.pi)), n - 1).astype(np.intp)

    def _zenith_cells(self, horiz: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.intp]:
        n = self.config.zen_bins
        zen = np.arctan2(horiz, -z)                            # zenith distance from "up" (-z in NED), [0, pi]
        return np.minimum(zen * (n / math.pi), n - 1).astype(np.intp)

    def predict(self, dt_s: float, v_h_k: NDArray[np.float64], v_h_k1: NDArray[np.float64], yaw_rate_k: float,
                yaw_rate_k1: float, rng: np.random.Generator) -> None:
        """Time update, eq. (14), then ageing and removal."""
        cfg = self.config
        if dt_s <= 0.0:
            return
        n = len(self)
        psi0 = dt_s * (yaw_rate_k + yaw_rate_k1) / 2.0
        self._yaw_total_rad += psi0
        if not n:
            return
        # eq. (14): u_j = dT (v_k + v_k+1 + n_v,j) / 2, psi_j = dT (psidot_k + psidot_k+1 + n_psi,j) / 2
        u0 = (dt_s / 2.0) * (np.asarray(v_h_k, dtype=float) + np.asarray(v_h_k1, dtype=float))
        d = self._p - u0[:, None]                              # p_j - u_j
        c0, s0 = math.cos(psi0), math.sin(psi0)
        if cfg.velocity_noise_m_s > 0.0 or cfg.yaw_rate_noise_rad_s > 0.0:
            # n_v (rows 0-2) and n_psi (row 3), drawn in float32 (cheaper; the noise needs no more digits),
            # scaled by float64 factors so that the arithmetic stays in float64
            noise = rng.standard_normal((4, n), dtype=np.float32)
            d -= noise[:3] * np.float64(dt_s / 2.0 * cfg.velocity_noise_m_s)
            c, s = _rotate_cos_sin(c0, s0, noise[3] * np.float64(dt_s / 2.0 * cfg.yaw_rate_noise_rad_s))
        else:
            c, s = np.full(n, c0), np.full(n, s0)
        p = np.empty((3, n))                                   # Rz(psi_j)^T (p_j - u_j)
        np.multiply(c, d[0], out=p[0])
        p[0] += s * d[1]
        np.multiply(c, d[1], out=p[1])
        p[1] -= s * d[0]
        p[2] = d[2]
        ages = self.ages_s + dt_s
        keep = ages <= cfg.max_age_s
        if cfg.near_field_max_age_s > cfg.max_age_s and not keep.all():
            held = (ages <= cfg.near_field_max_age_s) & (p[0] * p[0] + p[1] * p[1] <= cfg.near_field_m**2)
            keep |= held
        keep &= np.einsum("ij,ij->j", d, d) <= cfg.radius_m**2
        if keep.all():
            self._set_particles(p, ages, self.open_top)
        else:
            self._set_particles(np.compress(keep, p, axis=1), np.compress(keep, ages), np.compress(keep, self.open_top))

    def measure(self, stamp_s: float, obs: SectorObservation, rng: np.random.Generator | None = None,
                unseen_points_h_m: NDArray[np.float64] | None = None) -> None:
        """Measurement step: carve free space, overwrite the measured cells, record observed sectors.

        With ``rng`` the ``copies`` of a measured point are drawn around it with the measurement noise
        (``measurement_noise_per_m`` x its distance), as a particle filter samples its measurement model;
        the nearest of them then errs on the near side, the safe one. Without, the copies sit on the point.
        ``unseen_points_h_m`` (K x 3, H): objects this frame did not see but inferred
        (:mod:`perception.hidden_floor`), measured as the seen points are."""
        self._last_stamp = stamp_s
        points_h_m = obs.points_h_m
        open_top = obs.open_top if obs.open_top is not None else np.zeros(points_h_m.shape[0], dtype=bool)
        if unseen_points_h_m is not None and unseen_points_h_m.shape[0]:
            unseen = np.asarray(unseen_points_h_m, dtype=float).reshape(-1, 3)
            points_h_m = np.concatenate([points_h_m, unseen])
            open_top = np.concatenate([open_top, np.ones(unseen.shape[0], dtype=bool)])
        if len(self) or points_h_m.shape[0]:
            self._measure_points(obs, points_h_m, open_top, rng)
        self._mark_observed(stamp_s, obs)

    def _measure_points(self, obs: SectorObservation, points_h_m: NDArray[np.float64], open_top: NDArray[np.bool_],
                        rng: np.random.Generator | None = None) -> None:
        cfg = self.config
        n, k = len(self), points_h_m.shape[0]
        # the particles and the measured points side by side: each vectorised step runs once for both
        p = np.concatenate([self._p, points_h_m.T], axis=1) if k else self._p
        az, horiz = _polar(p[0], p[1]) if k else self._polar_of_particles()
        remove = np.zeros(n, dtype=bool)
        if n:
            # free space: in view and nearer than the sector's measured range by the margin (inf: free to
            # the sensor's range; nan, and -1 = out of view, which indexes the appended nan: never carved)
            sec, rng_p = obs.sector_and_range_of_points_h(p[:, :n].T)
            remove = rng_p < np.concatenate((obs.ranges_m - cfg.carve_margin_m, _NAN))[sec]
            # near the blind zone a sector's reading does not prove free space (issue 14: a wall 0.5 m ahead,
            # partly inside the minimum range, was carved away by the farther pixels of the same sectors
            # and the vehicle, no longer seeing it, was pushed to 0.18 m of it)
            remove &= rng_p >= obs.min_range_m + cfg.carve_blind_margin_m
        if k:
            # measured cells are overwritten; the zenith only where the azimuth is a measured one (the
            # candidates end with the k measured points themselves, in order)
            ia = self._azimuth_cells(az)
            measured_az = np.zeros(cfg.az_bins, dtype=bool)
            measured_az[ia[n:]] = True
            cand = measured_az[ia].nonzero()[0]
            cells = ia[cand] * cfg.zen_bins + self._zenith_cells(horiz[cand], p[2, cand])
            measured = np.zeros(cfg.az_bins * cfg.zen_bins, dtype=bool)
            measured[cells[-k:]] = True
            remove[cand[:-k]] |= measured[cells[:-k]]
        if n:
            # Particles nearer the camera than its minimum range are in its blind zone: the sector's reading
            # (the background past an obstacle the vehicle is now too close to see) says nothing about them,
            # so they are neither carved nor overwritten.
            remove &= rng_p >= obs.min_range_m
        if not k and not remove.any():
            return
        # the survivors, then `copies` new particles at each measured point
        idx = np.concatenate([(~remove).nonzero()[0], np.repeat(np.arange(n, n + k), cfg.copies)])
        ages = np.concatenate([self.ages_s, np.zeros(k)]) if k else self.ages_s
        tops = np.concatenate([self.open_top, open_top]) if k else self.open_top
        if k and rng is not None and cfg.measurement_noise_per_m > 0.0:
            new = p[:, idx]     # a copy: the new particles are its last k * copies columns
            fresh = new[:, new.shape[1] - k * cfg.copies:]
            sigma = cfg.measurement_noise_per_m * np.sqrt(np.einsum("ij,ij->j", fresh, fresh))
            fresh += rng.standard_normal(fresh.shape) * sigma
            self._set_particles(new, ages[idx], tops[idx])
        else:
            self._set_particles(p[:, idx], ages[idx], tops[idx], az[idx], horiz[idx])
        if len(self) > cfg.max_particles:  # oldest go first
            order = np.argsort(self.ages_s, kind="stable")[: cfg.max_particles]
            self._set_particles(self._p[:, order], self.ages_s[order], self.open_top[order])

    def _mark_observed(self, stamp_s: float, obs: SectorObservation) -> None:
        """Sectors seen by this frame (a point or free space), kept in world azimuth."""
        # azimuths of the rays of the seen sectors, not looking straight up or down (Python floats: a few
        # dozen values, where numpy calls cost more than the arithmetic)
        az = [math.atan2(y, x) for (x, y, _), r in zip(obs.rays_h.tolist(), obs.ranges_m.tolist(), strict=True)
              if not math.isnan(r) and x * x + y * y > 0.05**2]
        if not az:
            return
        # the camera's sectors are wider than 5°: mark every sector the azimuth span of the rays touches
        centre = math.atan2(sum(map(math.sin, az)), sum(map(math.cos, az)))
        rel = [(a - centre + math.pi) % (2 * math.pi) - math.pi for a in az]
        inc = 2 * math.pi / self.config.sectors
        start = centre + self._yaw_total_rad + inc / 2
        first = math.floor((start + min(rel)) / inc)
        last = math.floor((start + max(rel)) / inc)
        self._observed_s[np.arange(first, last + 1) % self.config.sectors] = stamp_s

    def _sector_index(self, az_rad: NDArray[np.floating[Any]]) -> NDArray[np.intp]:
        return sector_index(az_rad, self.config.sectors)

    def sectors(self, stamp_s: float, floor_drop_m: float | None = None) -> ObstacleSectors:
        """The OBSTACLE_DISTANCE-style summary at ``stamp_s``: per sector the nearest particle within the height
        band (``floor_drop_m``: the floor's depth below the vehicle, H z down, when known: particles within
        ``floor_margin_m`` of it are left out), else inf where observed lately, else NaN (unknown)."""
        cfg = self.config
        n = cfg.sectors
        # observed flags, from world azimuth back to H: H sector i is world sector i + k0 (accumulated yaw)
        k0 = math.floor((self._yaw_total_rad + math.pi / n) / (2 * math.pi / n)) % n
        obs_age = stamp_s - np.concatenate((self._observed_s[k0:], self._observed_s[:k0]))
        dist = np.where(obs_age <= cfg.max_age_s, np.inf, np.nan)
        if len(self):
            az, horiz = self._polar_of_particles()
            in_band = np.abs(self._p[2]) <= cfg.z_band_m
            if floor_drop_m is not None and math.isfinite(floor_drop_m):
                in_band &= self._p[2] < floor_drop_m - cfg.floor_margin_m
            band = in_band.nonzero()[0]
            if band.size:
                best = np.full(n, np.inf)     # nearest horizontal distance per sector within the height band
                np.minimum.at(best, self._sector_index(az[band]), horiz[band])
                dist = np.where(best < np.inf, np.maximum(best, cfg.min_distance_m), dist)
        return ObstacleSectors(stamp_s, dist, 360.0 / n, 0.0, cfg.min_distance_m, cfg.max_distance_m)

    def nearest_h(self) -> NDArray[np.float64] | None:
        if not len(self):
            return None
        i = int(np.argmin(np.einsum("ij,ij->j", self._p, self._p)))
        return self._p[:, i].copy()


def _polar(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Azimuth in [-pi, pi] and horizontal distance of points in H."""
    return np.arctan2(y, x), np.sqrt(x * x + y * y)


def _rotate_cos_sin(c0: float, s0: float, delta: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                               NDArray[np.float64]]:
    """cos and sin of psi0 + delta_j from cos/sin of psi0 and small per-particle angles delta_j.

    The yaw noise of one frame is ~1e-3 rad: Taylor terms to delta^5 are exact in double precision below
    1e-2 rad and cost a fraction of np.cos/np.sin; larger angles take the library functions.
    """
    if float(np.abs(delta).max()) < 1e-2:
        d2 = delta * delta
        cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0))
        sd = delta * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
    else:
        cd, sd = np.cos(delta), np.sin(delta)
    return c0 * cd - s0 * sd, s0 * cd + c0 * sd
