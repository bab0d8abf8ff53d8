"""Solver settings as frozen dataclasses; every default lives here."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .errors import ConfigError

__all__ = ["Tolerances", "SolverConfig", "TOL"]


@dataclass(frozen=True)
class Tolerances:
    """Numeric tolerances, one comment per value (cf. trimesh ToleranceMesh)."""

    #: triangles with area below this fraction of (scene diagonal)^2 are degenerate
    degenerate_area: float = 1e-14
    #: ray origins move off their surface by this fraction of the scene diagonal
    ray_offset: float = 2e-6
    #: relative closure the energy ledger must reach (float64 round-off)
    ledger: float = 1e-9
    #: back-face share of shot power above which we warn about flipped normals
    backface_warn: float = 0.05


TOL = Tolerances()


@dataclass(frozen=True)
class SolverConfig:
    """Progressive-refinement settings.

    ===================  =====  ==============================================  ========
    name                 type   meaning                                         default
    ===================  =====  ==============================================  ========
    seed                 int    seed of every random stream in a run           0
    tol                  float  stop when unshot/emitted power falls below      0.01
    time_limit           float  stop after this many wall seconds (0: none)     0
    max_rays             int    stop after this many rays in all (0: none)      0
    rays_per_power       float  rays spent per unit of the *emitted* power,     2e5
                                expressed as rays for shooting all of it once
    min_rays             int    fewest rays for one shot (M_min)                32
    max_rays_per_shot    int    most rays for one shot (M_max)                  65536
    batch_rays           int    rays per Embree call (top-K shooters at once)   262144
    max_shooters         int    most patches shot in one Embree call (K)        4096
    snapshot_factor      float  snapshots at geometric steps of this ratio      1.25
    overshoot            float  ambient overshooting strength (0: plain         1.0
                                progressive refinement; see solve.py)
    overshoot_min_return float  overshoot only when the measured return ratio   0.85
                                (reflected / shot) is at least this (stiff)
    stiff_rays           bool   in stiff scenes budget rays against the whole   True
                                solution E/(1-lambda), not the emitted power
    adaptive_bins        bool   twin entries weaker than one ray are shot from  True
                                coarser direction blocks (boundary.coarsen_
                                directions); False: every bin on its own
    ===================  =====  ==============================================  ========

    Rays per shot are proportional to the power shot (a fixed power per ray,
    ``emitted / rays_per_power``), clamped to [min_rays, max_rays_per_shot].
    A stiff scene (return ratio lambda >= overshoot_min_return) shoots
    E/(1-lambda) in all, up to 1000 times its emission at rho 0.999; with
    ``stiff_rays`` the power per ray grows by sqrt((1-overshoot_min_return)/(1-lambda))
    (and the min_rays floor shrinks by it), which keeps the noise relative to B
    about that of an ordinary scene (see solve.py).
    """

    seed: int = 0
    tol: float = 0.01
    time_limit: float = 0.0
    max_rays: int = 0
    rays_per_power: float = 2e5
    min_rays: int = 32
    max_rays_per_shot: int = 65536
    batch_rays: int = 262144
    max_shooters: int = 4096
    snapshot_factor: float = 1.25
    overshoot: float = 1.0
    overshoot_min_return: float = 0.85
    stiff_rays: bool = True
    adaptive_bins: bool = True

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ConfigError(f"invalid solver setting: {what}")

        need(0.0 <= self.tol < 1.0 and math.isfinite(self.tol), f"tol={self.tol} must be in [0, 1)")
        need(self.time_limit >= 0, f"time_limit={self.time_limit} must be >= 0")
        need(self.max_rays >= 0, f"max_rays={self.max_rays} must be >= 0")
        need(self.rays_per_power > 0, f"rays_per_power={self.rays_per_power} must be > 0")
        need(1 <= self.min_rays <= self.max_rays_per_shot,
             f"need 1 <= min_rays ({self.min_rays}) <= max_rays_per_shot ({self.max_rays_per_shot})")
        need(self.batch_rays >= self.max_rays_per_shot,
             f"batch_rays={self.batch_rays} must be >= max_rays_per_shot={self.max_rays_per_shot}")
        need(self.max_shooters >= 1, f"max_shooters={self.max_shooters} must be >= 1")
        need(self.snapshot_factor > 1.0, f"snapshot_factor={self.snapshot_factor} must be > 1")
        need(0.0 <= self.overshoot <= 1.0, f"overshoot={self.overshoot} must be in [0, 1]")
        need(0.0 < self.overshoot_min_return < 1.0,
             f"overshoot_min_return={self.overshoot_min_return} must be in (0, 1)")

    def replace(self, **changes) -> "SolverConfig":
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)
