"""What the mesh's adaptive refinement (mesh.adapt) buys: the direct light as the pictures show it.

Per scene, the automatic mesh without and with refinement: elements, the refinement's seconds and
shadow rays, and the error of the direct light a piecewise mesh can show, with the solver's noise
left out.  Each element takes its exact mean direct irradiance (photometry.direct_irradiance over
the triangle); the pictures' smoothed values (render.CornerSmoother: corners averaged over
neighbours, interpolated across the element) and the flat element values are compared with the
exact direct irradiance at --points area-sampled points of the lit reflecting surfaces (each point
faces its element's front).  Printed: RMS(shown - exact) / RMS(exact), smoothed and flat, over
all points, and in the room (points farther than an element from a lamp and lit under FIXTURE x the
mean: not in fixtures), also
relative to the light there (exact + the room's mean reflected light); beside them, the same count
of elements spent uniformly (a finer automatic mesh), and the unrefined mesh at a sixth of the free
path (the automatic mesh before refinement).  No assertions.

Run: .venv/bin/python bench/bench_adapt.py [--scenes 'cornell;office;...'] [--points 40000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT.parent / "shared" / "models"
sys.path.insert(0, str(ROOT))

#: points lit over this many times the mean direct light are inside a fixture
FIXTURE = 20.0

DEFAULT = ";".join(["cornell", "office", "office:rows=3,cols=2,seed=21,room=5,height=3.2"] + [
    str(MODELS / m / "scene.obj") for m in ("office2", "classroom", "office3", "icecream_store")])


def shown_error(patches, size: float, points: int, seed: int = 5) -> dict:
    """RMS of the smoothed and the flat direct light against the exact one (photometry.shown_direct)
    at area-sampled points of the reflecting, non-emitting front patches that are not panes: over
    all points, in the room, and relative to the light there."""
    from dcrad.meshing.mesh import near_lamps
    from dcrad.outputs.photometry import Y_WEIGHTS, shown_direct

    lit = (~patches.is_back) & (patches.rho.max(axis=1) > 0) & (patches.emission.max(axis=1) == 0)
    if patches.glazing is not None:
        lit &= ~patches.glazing.mask
    got = shown_direct(patches, np.flatnonzero(lit), points, seed)
    smooth, flat, truth = got["shown"], got["flat"], got["exact"]
    scale = np.sqrt(np.mean(truth ** 2))
    rho = float(patches.mean_rho @ Y_WEIGHTS)
    room = float(np.mean(truth)) * rho / (1 - rho)
    # the room: leave out the fixtures, points within an element of a lamp (a lamp's housing beside
    # its emitter holds 97% of the classroom's squared error, 99% of office2's, and nobody reads it)
    # or lit over FIXTURE x the mean (8 points inside office3's lamp shades, at 160x the mean, held
    # 90% of its squared error)
    lamps = patches.triangles[patches.emission.max(axis=1) > 0]
    inside = ~near_lamps(np.floor(got["at"] / size).astype(np.int64), lamps, size) & \
        (truth <= FIXTURE * np.mean(truth))
    scale_in = np.sqrt(np.mean(truth[inside] ** 2))

    def rms(x):
        return float(np.sqrt(np.mean((x - truth) ** 2)) / scale)

    def rel(x):
        return float(np.sqrt(np.mean(((x - truth) / (truth + room))[inside] ** 2)))

    def rms_in(x):
        return float(np.sqrt(np.mean((x - truth)[inside] ** 2)) / scale_in)

    return {"smooth": rms(smooth), "flat": rms(flat), "rel": rel(smooth), "room": rms_in(smooth),
            "room_share": float(inside.mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=DEFAULT, help="';'-separated scene files or built-in specs")
    ap.add_argument("--points", type=int, default=40000)
    args = ap.parse_args()
    from dcrad.io.scene import load_scene
    from dcrad.meshing.mesh import PATHS_PER_ELEMENT
    from dcrad.pipeline import default_patch_size, resolve_scene

    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.scenes.split(";"):
            path = resolve_scene(spec, Path(tmp) / spec.replace(":", "_").replace(",", "_").replace("=", ""))
            scene = load_scene(path)
            size = default_patch_size(scene)
            plain = scene.patches(size)
            t0 = time.perf_counter()
            fine = scene.patches(size, adapt=True)
            seconds = time.perf_counter() - t0
            a = shown_error(plain, size, args.points)
            b = shown_error(fine, size, args.points)
            # the same count of elements spent uniformly: a finer automatic mesh
            same = scene.patches(size * np.sqrt(len(plain) / len(fine)))
            c = shown_error(same, size, args.points)
            # the mesh before refinement was built: a sixth of the free path, unrefined
            sixth = scene.patches(size * PATHS_PER_ELEMENT / 6.0)
            d = shown_error(sixth, size, args.points)
            done = fine.adapted or {}
            name = Path(spec).parent.name if spec.endswith(".obj") else spec
            print(f"{name}: size {size:.3g} m; elements {len(plain)} -> {len(fine)} (unknowns {plain.units} -> "
                  f"{fine.units}), {done.get('split', 0)} split in {done.get('levels', 0)} rounds, "
                  f"{done.get('rays', 0):,} shadow rays, {seconds:.2f} s meshing; direct light shown, RMS / RMS: "
                  f"smoothed {a['smooth']:.2%} -> {b['smooth']:.2%}, flat {a['flat']:.2%} -> {b['flat']:.2%}; "
                  f"the same elements spent uniformly ({len(same)}): smoothed {c['smooth']:.2%}, flat {c['flat']:.2%}; "
                  f"in the room ({b['room_share']:.0%} of points), smoothed: {a['room']:.2%} -> {b['room']:.2%} "
                  f"(uniformly {c['room']:.2%}), relative {a['rel']:.2%} -> {b['rel']:.2%} (uniformly {c['rel']:.2%}); "
                  f"a sixth of the free path unrefined ({len(sixth)} elements): in the room {d['room']:.2%}, "
                  f"relative {d['rel']:.2%}",
                  flush=True)


if __name__ == "__main__":
    main()
