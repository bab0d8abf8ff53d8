"""Solver settings as frozen dataclasses; every default lives here."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from dcrad.errors import ConfigError

__all__ = ["Tolerances", "SolverConfig", "DivideConfig", "BOUNDARY_MODES", "TOL", "setting", "divide_flags_set",
           "unused_divide_note"]


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
    #: escaped share of the shot power above which we warn (lights facing away from everything;
    #: an open box loses 30% of it, a lamp over a bare floor 72%)
    escape_warn: float = 0.9


TOL = Tolerances()


def setting(default, help: str, flag: bool = True):
    """A settings field: its default and its one-line meaning.

    The meaning is the field's ``--flag`` help, and ``dcrad.settings`` maps every
    field to the command line, the wire (``dcrad.v1.SolverSettings``, same name)
    and back; ``flag=False`` keeps it off the command line.
    """
    return field(default=default, metadata={"help": help, "flag": flag})


#: the most rays for shooting the emitted power once (``rays_per_power``, set or chosen from the
#: accuracy): at about 2M rays/s a core, 1e13 rays are two months
MAX_RAYS_PER_POWER = 1e13
#: the most rays of one batch (Embree call): 2^23 rays of about 200 bytes each in flight is 1.7 GB
MAX_BATCH_RAYS = 1 << 23

@dataclass(frozen=True)
class SolverConfig:
    """Progressive-refinement settings; each field's help says what it means.

    Every field travels: ``dcrad.settings`` derives the ``--flags``, the proto
    message (``SolverSettings``, a field of the same name with presence) and the
    report's ``settings`` from these fields.  To add one: a line here, a line in
    ``SolverSettings`` in proto/dcrad/v1/dcrad.proto, ``make proto``.

    Rays per shot are proportional to the power shot (a fixed power per ray,
    ``emitted / rays_per_power``), clamped to [min_rays, max_rays_per_shot].
    A stiff scene (return ratio lambda >= overshoot_min_return) shoots
    E/(1-lambda) in all, up to 1000 times its emission at rho 0.999; with
    ``stiff_rays`` the power per ray grows by sqrt((1-overshoot_min_return)/(1-lambda))
    (and the min_rays floor shrinks by it), which keeps the noise relative to B
    about that of an ordinary scene (see solver.py).
    """

    seed: int = setting(0, "seed of every random stream in a run")
    accuracy: float = setting(0.02, "target estimated RMS error over RMS of the reflected light B - E: the "
                                    "solver chooses the ray density and stops when its estimate meets it "
                                    "(used while --tol is 0; see dcrad/solving/accuracy.py)")
    direct: bool = setting(True, "gather the direct light with shadow rays from every patch to the emitters "
                                 "(next-event estimation) before shooting the reflected light; single-subscene "
                                 "runs (dcrad/transport/direct.py)")
    shadow_rays: int = setting(0, "shadow rays per receiving patch for the direct light (0: from --accuracy)")
    tol: float = setting(0.0, "expert: stop when the residual (unshot + in flight) / emitted falls to this "
                              "instead of by --accuracy (0: by --accuracy; 0.01 when --accuracy is 0 too)")
    time_limit: float = setting(0.0, "stop after this many wall seconds (0: none)")
    max_rays: int = setting(0, "stop after this many rays in all (0: none)")
    rays_per_power: float = setting(0.0, "expert: rays for shooting the emitted power once, which sets the power "
                                         "per ray (0: chosen from --accuracy and the patch count; 2e5 with --tol)")
    min_rays: int = setting(32, "fewest rays for one patch shot (M_min)")
    max_rays_per_shot: int = setting(65536, "most rays for one patch shot (M_max)")
    batch_rays: int = setting(262144, "rays per Embree call (the top-K shooters at once)")
    max_shooters: int = setting(4096, "most patches shot in one Embree call (K)")
    snapshot_factor: float = setting(1.25, "snapshots of B at geometric steps of this ratio of rays")
    snapshot_mb: float = setting(128.0, "MB cap on the snapshots of B kept for the error curve (float16; "
                                        "past it every other snapshot is dropped)")
    overshoot: float = setting(1.0, "ambient overshooting strength in stiff scenes (0: plain progressive "
                                    "refinement; see solver.py)")
    overshoot_min_return: float = setting(0.85, "overshoot only when the measured return ratio (reflected / "
                                                "shot) is at least this (a stiff scene)")
    stiff_rays: bool = setting(True, "in stiff scenes budget rays against the whole solution E/(1-lambda), "
                                     "not the emitted power")
    adaptive_bins: bool = setting(True, "twin entries weaker than one ray are shot from coarser direction "
                                        "blocks (boundary.coarsen_directions); off: every bin on its own")

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ConfigError(f"invalid solver setting: {what}")

        need(0.0 <= self.tol < 1.0 and math.isfinite(self.tol), f"tol={self.tol} must be in [0, 1)")
        need(self.time_limit >= 0, f"time_limit={self.time_limit} must be >= 0")
        need(self.max_rays >= 0, f"max_rays={self.max_rays} must be >= 0")
        need(0 <= self.rays_per_power <= MAX_RAYS_PER_POWER,
             f"rays_per_power={self.rays_per_power} must be in [0, {MAX_RAYS_PER_POWER:.0e}] (0: automatic; "
             f"{MAX_RAYS_PER_POWER:.0e} rays are months of tracing)")
        need(self.shadow_rays >= 0, f"shadow_rays={self.shadow_rays} must be >= 0 (0: automatic)")
        need(0.0 <= self.accuracy < 1.0 and math.isfinite(self.accuracy),
             f"accuracy={self.accuracy} must be in [0, 1) (a fraction of the reflected light; 0: off)")
        need(1 <= self.min_rays <= self.max_rays_per_shot,
             f"need 1 <= min_rays ({self.min_rays}) <= max_rays_per_shot ({self.max_rays_per_shot})")
        need(self.batch_rays >= self.max_rays_per_shot,
             f"batch_rays={self.batch_rays} must be >= max_rays_per_shot={self.max_rays_per_shot}")
        need(self.batch_rays <= MAX_BATCH_RAYS,
             f"batch_rays={self.batch_rays} must be <= {MAX_BATCH_RAYS} (a batch's rays are held in memory at once, "
             f"about 200 bytes each)")
        need(0 <= self.seed < 2**63, f"seed={self.seed} must be in [0, 2^63)")
        need(self.max_shooters >= 1, f"max_shooters={self.max_shooters} must be >= 1")
        need(self.snapshot_factor > 1.0, f"snapshot_factor={self.snapshot_factor} must be > 1")
        need(self.snapshot_mb > 0, f"snapshot_mb={self.snapshot_mb} must be > 0")
        need(0.0 <= self.overshoot <= 1.0, f"overshoot={self.overshoot} must be in [0, 1]")
        need(0.0 < self.overshoot_min_return < 1.0,
             f"overshoot_min_return={self.overshoot_min_return} must be in (0, 1)")

    def replace(self, **changes) -> "SolverConfig":
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


#: boundary modes: the paper's binned twins, or exact ray forwarding
BOUNDARY_MODES = ("binned", "exact")


@dataclass(frozen=True)
class DivideConfig:
    """Divide-and-conquer settings; each field's help says what it means (``dcrad.settings``).

    ``iterations`` is doIterations' n: 0 (the default) is adaptive, each subscene
    iterates until its own residual has fallen to a quarter (or below its share of
    tol/2), at most ``max_iterations`` batches; N > 0 is exactly N batches per
    subscene between two barriers (fewer only when nothing is left to shoot).
    """

    subscenes: int = setting(2, "number of cells k (1: no partition, no twins)")
    iterations: int = setting(0, "batches per subscene between barriers (0: adaptive, at most max_iterations)")
    # long enough that barriers are few against the work between them: on the office 8x8 on 2 workers
    # 256 needed half the barriers of 64 and a shorter critical path (bench/RESULTS.md)
    max_iterations: int = setting(256, "most batches per subscene between barriers when adaptive")
    solid: int = setting(8, "direction bins per side of a portal cell: SOLIDANGLES = solid^2")
    cell_size: float = setting(0.0, "portal cell edge in m (0: 1/128 of the scene diagonal)")
    mode: str = setting("exact", "boundary mode: exact ray forwarding (unbiased at any k), or the paper's "
                                 "binned twins (biased where a boundary crosses open space)")

    @property
    def adaptive(self) -> bool:
        return self.iterations == 0

    @property
    def batches_per_barrier(self) -> int:
        return self.max_iterations if self.adaptive else self.iterations

    def __post_init__(self):
        bad = [f"{name}={getattr(self, name)!r} must be {rule}" for name, ok, rule in (
            ("subscenes", self.subscenes >= 1, ">= 1"),
            ("iterations", self.iterations >= 0, ">= 0 (0: adaptive)"),
            ("max_iterations", self.max_iterations >= 1, ">= 1"),
            ("solid", self.solid >= 1, ">= 1"),
            ("cell_size", self.cell_size >= 0, ">= 0 (0: automatic)"),
            ("mode", self.mode in BOUNDARY_MODES, f"one of {', '.join(BOUNDARY_MODES)}")) if not ok]
        if bad:
            raise ConfigError(f"invalid divide setting: {'; '.join(bad)}")

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def divide_flags_set(divide: DivideConfig) -> list[str]:
    """The divided-run flags of ``divide`` set away from their defaults, as the user wrote them
    (``--iterations 8``; ``mode`` is ``--boundary``: settings.add_divide_flags); the subscene count aside."""
    default = DivideConfig()
    flags = []
    for f in dataclasses.fields(DivideConfig):
        value = getattr(divide, f.name)
        if f.name != "subscenes" and value != getattr(default, f.name):
            flags.append(("--boundary" if f.name == "mode" else "--" + f.name.replace("_", "-")) + f" {value}")
    return flags


def unused_divide_note(divide: DivideConfig | None, run: str) -> str | None:
    """The report's sentence when divided-run flags were given to a run that did not divide (``run``
    says how it ran), or None: a flag that does not apply is reported, never silently dropped."""
    flags = divide_flags_set(divide) if divide is not None else []
    if not flags:
        return None
    return (f"{', '.join(flags)}: for divided runs only; this run {run}, so "
            f"{'it was' if len(flags) == 1 else 'they were'} not used")

