"""One solve from scene file to output folder, without networking.

``prepare`` loads and meshes a scene; ``solve_to`` runs the solver and writes
every output (radiosity.npz, patches.ply, scene.glb, preview images,
report.json).  The CLI and the services call these; they hold no numerics.
"""

from __future__ import annotations

import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

import scenes
from dcrad.choices import Choice
from dcrad.config import SolverConfig
from dcrad.errors import ConfigError, SceneError
from dcrad.io import export
from dcrad.io.scene import NO_EMITTERS, load_scene
from dcrad.meshing import mesh
from dcrad.meshing.patches import Patches
from dcrad.outputs import daylight, photometry, render
from dcrad.outputs.report import TIMINGS, RunBooks, run_report, write_json
from dcrad.runs import Divided, RunHooks, Single
from dcrad.solving.solver import Stats
from dcrad.transport import luminaires, punctual, sky
from dcrad.transport.rays import Tracer

__all__ = ["default_patch_size", "prepare", "write_outputs", "write_pictures", "solve_to", "resolve_scene",
           "finish_run"]

log = logging.getLogger("dcrad")


def default_patch_size(scene) -> float:
    """Automatic element size (m): from the scene's light scale, not its triangulation (mesh.py).

    The rays' mean free path / mesh.PATHS_PER_ELEMENT: the same for a building of 400 rooms as
    for one, and for a file triangulated finely or coarsely (the median input edge this used
    to follow meshed real models 8x to 65,000x too finely)."""
    return mesh_choice(scene)[0]


def mesh_choice(scene) -> tuple[float, str]:
    """(automatic element size m, the report's sentence on how it was found); cached on the scene."""
    if scene.element_choice is None:
        scene.element_choice = mesh.element_size(scene.vertices, scene.faces[scene.valid])
    return scene.element_choice


def resolve_scene(spec: str, workdir: Path) -> Path:
    """A scene path, or a built-in scene name with optional parameters.

    ``office``, ``cornell``, ``furnace`` or ``office:rows=3,cols=4,seed=2`` write the
    generated OBJ/MTL into ``workdir`` and return its path.  A file of that name wins; a folder
    does not (``dcrad solve cornell --out cornell`` run twice left a folder ``cornell`` that the
    second run took for the scene).
    """
    name, _, params = spec.partition(":")
    if Path(spec).is_file() or name not in scenes.names():
        return Path(spec)
    kwargs = {}
    for item in filter(None, params.split(",")):
        key, _, value = item.partition("=")
        try:
            kwargs[key.strip()] = int(value) if value.strip().lstrip("-").isdigit() else float(value)
        except ValueError:
            raise SceneError(f"built-in scene '{name}': parameter '{item}' is not key=number") from None
    try:
        return scenes.write_builtin(name, workdir, **kwargs)
    except TypeError as exc:
        raise SceneError(f"built-in scene '{name}': {exc}") from None


def light_sources(luminaires_path=None, daylight=None, scale: float = 1.0):
    """scene -> the light sources a run adds to the file's own: a luminaire schedule's
    (luminaires.load_schedule) and the sky's and sun's (sky.daylight_sources); None without either."""
    if luminaires_path is None and daylight is None:
        return None

    def sources(scene) -> tuple:
        out = tuple(luminaires.load_schedule(luminaires_path, scene, scale)) if luminaires_path is not None else ()
        return out + (sky.daylight_sources(daylight, scene) if daylight is not None else ())

    return sources


def prepare(path, patch_size: float | None = None, scale: float = 1.0, up: str | None = None,
            two_sided: bool = False, timings: dict | None = None, loaded: tuple | None = None,
            workplane: float = 0.0, adapt: bool | None = None, sources=None):
    """Load, validate and mesh a scene: returns (scene, patches, patch_size used).

    ``adapt``: refine where the direct light varies (mesh.adapt); None: when the size is automatic
    (``patch_size`` None or 0), not for an expert's --patch-size.  A second mesh of the same scene at
    the size the first one used (``compare``, references) passes the first one's ``adapt``.
    ``sources``: scene -> light sources besides the file's (luminaires), placed before meshing so
    that the refinement follows their light too.

    ``up`` (None: detect) and ``two_sided``: see scene.load_scene.  ``timings`` (a dict)
    receives ``load_s`` (file to validated triangles) and ``mesh_s`` (triangles to patches).
    ``loaded``: (scene, seconds[, patches]) of ``path`` loaded with these settings already, and
    meshed at this size (`dcrad solve`'s choice of workers loads and meshes it first; patches
    None: not meshed): not loaded or meshed twice.  ``workplane``: checked against the
    meshed scene (``photometry.check_workplane``).
    """
    t0 = time.perf_counter()
    if loaded is not None:
        scene, t0 = loaded[0], t0 - loaded[1]
    else:
        scene = load_scene(path, scale=scale, up=up, two_sided=two_sided)
    t1 = time.perf_counter()
    if patch_size is not None and not (math.isfinite(patch_size) and patch_size >= 0):
        raise ConfigError(f"--patch-size {patch_size}: must be a finite number of metres > 0 (0: automatic)")
    size = patch_size if patch_size else default_patch_size(scene)
    check_patch_count(mesh.estimate_elements(scene.vertices[scene.faces[scene.valid]], size), size)
    meshed = loaded[2] if loaded is not None and len(loaded) > 2 else None
    extra = tuple(sources(scene)) if sources is not None else ()
    if meshed is not None:
        patches = meshed
        patches.sources = (*patches.sources, *extra)
    else:
        patches = scene.patches(size, adapt=not patch_size if adapt is None else adapt, sources=extra)
    photometry.check_workplane(workplane, patches)
    if timings is not None:
        timings.update(load_s=t1 - t0, mesh_s=time.perf_counter() - t1)
    return scene, patches, size


#: memory a patch takes in a run, bytes (the 20x20 office: 2.2 GB for 1.27M patches in one
#: process, 3.3 GB divided; twins, snapshots and the outputs' views on top)
BYTES_PER_PATCH = 4096


def patch_limit() -> int:
    """The most patches a scene may be meshed into on this machine: its memory over
    BYTES_PER_PATCH, and at least a million."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        memory = 1 << 40
    return max(1_000_000, memory // BYTES_PER_PATCH)


def check_patch_count(estimate: int, size: float) -> None:
    """ConfigError when meshing to ``size`` would give more patches (about ``estimate``) than
    ``patch_limit``: a too-small --patch-size would otherwise exhaust the memory while meshing."""
    limit = patch_limit()
    if estimate > limit:
        raise ConfigError(f"--patch-size {size:.4g} m would mesh the scene into about {estimate:,} patches, more "
                          f"than the {limit:,} this machine's memory holds ({BYTES_PER_PATCH} bytes a patch); "
                          f"use a larger --patch-size (0: automatic)")


def scene_settings(scene, patch_size: float, scale: float, two_sided: bool = False,
                   workplane: float = 0.0) -> dict:
    """The report's scene settings: patch size, scale, up axis (and how it was found),
    two-sided (the flag; ``two_sided_triangles`` counts every two-sided input triangle),
    work-plane height, textured materials."""
    return {"patch_size_m": patch_size, "scale": scale, "up": scene.up, "up_source": scene.up_source,
            "two_sided": bool(two_sided),
            "two_sided_triangles": int(scene.two_sided.sum()) if scene.two_sided is not None else 0,
            "workplane_m": float(workplane), "textured_materials": list(scene.textured)}


def _is_floor_plan(patches: Patches) -> bool:
    """A multi-room floor: much wider than it is tall (internal frame: Y up, whatever the input's up axis)."""
    ext = patches.bounds[1] - patches.bounds[0]
    return max(ext[0], ext[2]) > 2.5 * max(ext[1], 1e-12)


@dataclass
class OutputViews:
    """What ``write_outputs`` needs that does not depend on B: the Embree scene of every patch, the
    preview camera and, for a floor plan, the cut-away mask, top-down camera and its Embree scene;
    built ahead (``output_views(ahead=True)``), also both views' primary hits and the corner
    smoothing's pairs, so that what is left once B is known is a gather and a sum.

    A coordinator makes it in a child process while its workers solve (coordinator/ahead.py): at
    1.27M patches the two Embree scenes took 6.0 s and the automatic camera 1.6 s of the outputs'
    18.7 s; at 201k patches the two views' rays and the corner pairs were 3.0 s of the
    coordinator's 5.4 s of outputs.
    """

    tracer: Tracer | None  #: None: built by the outputs if they trace (views made in another process)
    camera: render.Camera
    floor_plan: bool
    mask: np.ndarray | None = None
    top_camera: render.Camera | None = None
    top_tracer: Tracer | None = None
    hits: render.ViewHits | None = None  #: the preview camera's hits (ahead)
    top_hits: render.ViewHits | None = None  #: the top-down view's hits (ahead)
    smoother: render.CornerSmoother | None = None  #: the corner smoothing's pairs (ahead)
    live: render.ViewHits | None = None  #: the live preview's view (a coordinator's, ahead)


def live_view(scene, patches: Patches, width: int, height: int, tracer: Tracer | None = None,
              cut_tracer: Tracer | None = None) -> render.ViewHits:
    """The live preview's view (the status page): the scene's camera, a floor plan's top-down
    cut-away, or the automatic camera; one ray a pixel.  ``tracer`` (every patch) and
    ``cut_tracer`` (the cut-away's rows): Embree scenes to reuse; None: built here."""
    mask: np.ndarray | None = None
    if scene.camera:
        cam = render.camera_from_dict(scene.camera, width, height)
    elif _is_floor_plan(patches):
        cam, mask = render.topdown_camera(patches, width, height), render.cutaway_mask(patches)
    else:
        tracer = tracer if tracer is not None else Tracer.mesh(patches)
        cam = render.auto_camera(patches, width, height, tracer=tracer)
    if mask is None:
        return render.trace_view(patches, cam, None, tracer if tracer is not None else Tracer.mesh(patches))
    return render.trace_view(patches, cam, mask, cut_tracer if cut_tracer is not None else Tracer.mesh(patches, mask))


def output_views(scene, patches: Patches, width: int = 640, height: int = 480,
                 tracer: Tracer | None = None, top: bool = True, ahead: bool = False,
                 smoother: render.CornerSmoother | None = None, keep_tracers: bool = True,
                 live_size: tuple[int, int] | None = None) -> OutputViews:
    """The ``OutputViews`` of ``patches`` (``tracer``: an Embree scene over ``patches.triangles`` to
    reuse, the solve's; None: build one).  ``top`` False: the top-down Embree scene is left for
    ``write_outputs`` to build when it renders that view (one process: no two scenes held at once).
    ``ahead``: also trace both views (the top-down Embree scene is then freed) and form the corner
    pairs (``smoother``, if given, is used for them); ``keep_tracers`` False: no Embree scene is
    kept (the views go to another process; the outputs build one if they trace); ``live_size``
    (with ``ahead``): also the live preview's view (``OutputViews.live``), cast with the same
    Embree scenes."""
    tracer = tracer if tracer is not None else Tracer.mesh(patches)
    camera = (render.camera_from_dict(scene.camera, width, height) if scene.camera
              else render.auto_camera(patches, width, height, tracer=tracer))
    views = OutputViews(tracer, camera, False)
    if _is_floor_plan(patches):
        views.floor_plan, views.mask = True, render.cutaway_mask(patches)
        views.top_camera = render.topdown_camera(patches, width, height)
        views.top_tracer = Tracer.mesh(patches, views.mask) if top and not ahead else None
    if ahead:
        def top_view(top_camera: render.Camera) -> Tracer:
            cut = Tracer.mesh(patches, views.mask)
            views.top_hits = render.trace_view(patches, top_camera, views.mask, cut, samples=render.SAMPLES)
            return cut

        # the top-down view in a thread beside the preview's (Embree lets go of the GIL while it
        # traces): a views process at nice 19 that the solve starved finishes on both cores
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="top-view") as pool:
            top_done = pool.submit(top_view, views.top_camera) if views.top_camera is not None else None
            views.hits = render.trace_view(patches, camera, tracer=tracer, samples=render.SAMPLES)
            views.smoother = smoother if smoother is not None else render.CornerSmoother(patches)
            cut = top_done.result() if top_done is not None else None
        if live_size is not None:
            views.live = live_view(scene, patches, *live_size, tracer=tracer, cut_tracer=cut)
        del cut  # traced: the cut-away's Embree scene is not needed any more
    if not keep_tracers:
        views.tracer = views.top_tracer = None
    return views


def table_views(table: dict, names: list, camera: dict | None, width: int = 640, height: int = 480,
                live_size: tuple[int, int] | None = None) -> tuple[Patches, OutputViews]:
    """The patch table ``table`` (``Patches.table_arrays``) and its ``output_views(ahead=True)``,
    without Embree scenes: what a coordinator's views process makes (it gets the table, not the job)
    and keeps for ``write_pictures``; with ``live_size`` also the live preview's view
    (``OutputViews.live``)."""
    patches = Patches.from_table(table, names)
    scene = SimpleNamespace(camera=camera)
    return patches, output_views(scene, patches, width, height, ahead=True, keep_tracers=False, live_size=live_size)


def write_pictures(out: Path, patches: Patches, views: OutputViews, lux: np.ndarray, rotation=None,
                   tracer: Tracer | None = None) -> dict:
    """Write the outputs that read the smoothed corners: scene.glb, both views' preview.png/.exr and
    preview_top.png/.exr, illuminance.png (``patches.radiosity``: B; ``lux``: (n,) illuminance of each
    patch; ``rotation``: ``Scene.rotation``; ``tracer``: for views not traced ahead).

    returns {"written": {name: file} in the report's order, "view": the false colour's view,
    "legend_max_lux": its scale}.  A coordinator runs this in its views process (coordinator/ahead.py,
    from B and lux) while it writes the npz and PLY itself: the same function, the same files.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    exposure = render.scene_exposure(patches)
    # one smoothing pass for B and the false colour's channels (lux, front coverage, back
    # coverage: the smoother's, formed once), kept in float32 for the GLB and both views: 72 bytes
    # a patch, not 144
    smoother = views.smoother or render.CornerSmoother(patches, keep_pairs=0)
    both = smoother.apply(np.column_stack([patches.radiosity, lux]), dtype=np.float32, coverage=True)
    corners = both[..., :3]
    export.write_glb(out / "scene.glb", patches, corners, exposure=exposure, rotation=rotation)
    written["mesh"] = "scene.glb"

    camera = views.camera
    # each view is cast once: B (3 channels) and the false colour's (lux, front, back) together;
    # seen from behind, B shows the neutral flag grey and the false colour counts "back"
    flag = np.concatenate([np.multiply(render.BACKFACE_COLOR, 0.9 / exposure), [0.0, 0.0, 1.0 / np.pi]])
    hits = views.hits or render.trace_view(patches, camera, tracer=tracer, samples=render.SAMPLES)
    both_img = render.shade_view(hits, both, backface_color=flag)
    img = both_img[..., :3]
    export.write_png(out / "preview.png", render.tonemap(img, exposure=exposure, shoulder=render.SHOULDER))
    export.write_exr(out / "preview.exr", img)
    written["preview_png"] = "preview.png"
    written["preview_exr"] = "preview.exr"
    view = "preview camera"
    # the false colour marks where the light sources that are not surfaces sit (emitting surfaces
    # show themselves): its view's camera and Embree scene, to find the ones it shows
    fc_camera, fc_tracer = camera, views.tracer if views.tracer is not None else tracer
    if views.floor_plan and views.top_camera is not None:
        top_tracer = views.top_tracer
        if top_tracer is None and views.top_hits is None:
            top_tracer = Tracer.mesh(patches, views.mask)
        top_hits = views.top_hits or render.trace_view(patches, views.top_camera, views.mask, top_tracer,
                                                       samples=render.SAMPLES)
        fc_camera, fc_tracer = views.top_camera, top_tracer
        both_img = render.shade_view(top_hits, both, backface_color=flag)
        img = both_img[..., :3]
        export.write_png(out / "preview_top.png", render.tonemap(img, exposure=exposure, shoulder=render.SHOULDER))
        export.write_exr(out / "preview_top.exr", img)
        written["preview_top_png"] = "preview_top.png"
        written["preview_top_exr"] = "preview_top.exr"
        view = "top-down cut-away"
    # false colour of the last view (the floor plan if any)
    lamp = np.any(patches.emission > 0, axis=1)
    top = photometry.legend_scale(lux[~lamp], patches.area[~lamp])
    fc = both_img[..., 3:].astype(np.float64) * np.pi
    picture = photometry.false_colour(fc[..., 0], fc[..., 1], fc[..., 2], top)
    at = [s.position for s in patches.sources if getattr(s, "position", None) is not None]
    if at:
        if fc_tracer is None:
            fc_tracer = Tracer.mesh(patches) if fc_camera is camera else Tracer.mesh(patches, views.mask)
        render.draw_marks(picture, render.marks_in_view(fc_camera, np.array(at), fc_tracer), fc_camera.width)
    export.write_png(out / "illuminance.png", picture)
    written["illuminance_png"] = "illuminance.png"
    df = daylight.picture_scale(patches)
    if df is not None:  # the same view in daylight factors (percent of the sky's horizontal illuminance)
        export.write_png(out / "daylight_factor.png",
                         photometry.false_colour(fc[..., 0] * df, fc[..., 1], fc[..., 2], top * df, unit="DF %"))
        written["daylight_factor_png"] = "daylight_factor.png"
    return {"written": written, "view": view, "legend_max_lux": top}


def write_outputs(out: Path, scene, patches: Patches, width: int = 640, height: int = 480,
                  sections: dict | None = None, workplane: float = 0.0, tracer: Tracer | None = None,
                  views: OutputViews | None = None, painter=None) -> dict:
    """Write every output file; return {name: relative path} of what was written.

    Meshes are written in the input file's frame (``scene.rotation``); views use one
    exposure from the lit surfaces (render.scene_exposure).  ``sections`` (a dict)
    receives the report's ``photometry`` section; ``workplane`` > 0 adds a work-plane
    grid that many metres above the floor.  ``tracer``: an Embree scene over
    ``patches.triangles`` to reuse (the solve's; at 1.27M patches a second one cost
    4 s and 175 MB); None: build one.

    ``painter``: None, or a callable ``painter(out, radiosity, lux, rotation)`` returning a Future of
    ``write_pictures``' result, written by another process (a coordinator's views process) while this
    one writes radiosity.npz and patches.ply; if that fails, the pictures are written here (a warning
    says so) and the files are the same.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    views = views if views is not None else output_views(scene, patches, width, height, tracer, top=False)
    tracer = views.tracer
    patches.release_corners()  # 72 bytes a patch; the outputs read corners a view or chunk at a time
    h, gathered = photometry.irradiance(patches, tracer)
    lux = photometry.to_lux(h)
    del h
    painted = None
    if painter is not None:  # B and lux to the painter first: it works while this writes the arrays
        try:
            painted = painter(out, patches.radiosity, lux, scene.rotation)
        except Exception as exc:  # any failure there: the pictures are written here
            log.warning("the pictures could not be handed over (%s); writing them here", exc)
    grid = photometry.workplane(patches, workplane, tracer=tracer) if workplane > 0 else None
    extra = {"valid_input": scene.valid, "patch_E_lux": lux,
             "patch_L_cd_m2": photometry.luminance_cd(patches.radiosity)}
    if grid is not None:
        extra |= {"workplane_points": scene.to_input_frame(grid["points"]), "workplane_lux": grid["lux"]}
    sky = daylight.sky_of(patches)
    if sky is not None:
        extra["patch_daylight_factor"] = daylight.factor(lux, sky)
        if grid is not None:
            extra["workplane_daylight_factor"] = daylight.factor(grid["lux"], sky)
    # zlib lets go of the GIL: the compressed npz (5 s at 1.27M patches) is written beside the rest
    npz = ThreadPoolExecutor(max_workers=1, thread_name_prefix="npz")
    npz_done = npz.submit(export.write_radiosity_npz, out / "radiosity.npz", patches, len(scene.faces), extra)
    npz.shutdown(wait=False)
    written["radiosity"] = "radiosity.npz"
    export.write_patches_ply(out / "patches.ply", patches, rotation=scene.rotation)
    written["patches"] = "patches.ply"
    surfaces = photometry.surface_stats(patches, lux) if sections is not None else None  # beside the npz
    pictures = None
    if painted is not None:
        try:
            pictures = painted.result()
        except Exception as exc:  # the helper failed or died: the same pictures, written here
            log.warning("the pictures were not written beside the arrays (%s); writing them here", exc)
    if pictures is None:
        pictures = write_pictures(out, patches, views, lux, scene.rotation, tracer)
    written |= pictures["written"]
    npz_done.result()
    if sections is not None:
        section = {
            "efficacy_lm_per_W": photometry.EFFICACY, "Y_weights_rgb": photometry.Y_WEIGHTS.tolist(),
            "method": "E = 179 lm/W x Y(H), H = (B - E)/rho per channel; channels with rho < "
                      f"{photometry.RHO_GATHER:g}: the emitters' light from exact form factors x shadow-ray "
                      f"visibility, the reflected light gathered with {photometry.GATHER_RAYS} rays reading B - E; "
                      "L = 179 x Y(B) / pi",
            "gathered_patches": int(gathered.sum()),
            "legend_max_lux": pictures["legend_max_lux"],
            "view": pictures["view"],
            "surfaces": surfaces,
        }
        if grid is not None:
            section["workplane"] = {k: v for k, v in grid.items() if k not in ("points", "lux")}
            for room in section["workplane"].get("rooms", []):  # in the file's frame, like the points
                room["centre"] = scene.to_input_frame(np.array([room["centre"]]))[0].tolist()
        sections["photometry"] = section
        lums = luminaires.report_section(patches, grid, tracer)
        if lums is not None:
            sections["luminaires"] = lums
        lit = daylight.section(patches, surfaces, grid)
        if lit is not None:
            sections["daylight"] = lit
    return written


def finish_run(out: Path | None, scene, books: RunBooks, scene_values: dict, width: int = 640, height: int = 480,
               extra: dict | None = None, tracer: Tracer | None = None, views: OutputViews | None = None,
               painter=None) -> dict:
    """Write every output and report.json for a finished run; return the report.

    The one ending of every path (``solve_to`` single and divided, the
    coordinator's jobs).  The report's settings are the run's SolverConfig as it
    ran (``books.config``) and ``scene_values`` (``scene_settings``); ``extra``: more
    top-level report sections (the service's error curve).  ``books.timings`` gains
    ``outputs_s``.  ``tracer``: the solve's Embree scene over ``books.patches``, reused
    by the outputs (None: they build one); ``views``: the outputs' views built ahead
    (``output_views``; None: built here); ``painter``: who writes the pictures (``write_outputs``).
    ``out`` None (``dcrad.solve`` without a folder): nothing is written; the report's ``outputs``
    is empty and it has no ``photometry`` section (the outputs compute the lux).
    """
    settings = books.config.as_dict() | scene_values
    t0 = time.perf_counter()
    # light sources that are not patches light a scene file without emitters (a divided run books the
    # sky's light as what landed on what reflects: none in a black room, which the sky lights all the same)
    lit = bool(np.any(books.ledger.emitted)) or any(np.any(s.power()) for s in books.patches.sources)
    warnings = [w for w in scene.warnings if not (lit and w == NO_EMITTERS)] + books.warnings()
    size = float(settings.get("patch_size_m") or 0.0)
    auto = scene.element_choice if scene.element_choice is not None and scene.element_choice[0] == size else None
    p = books.patches
    front = ~p.is_back
    adapted = p.adapted
    table = mesh.mesh_table(p.names, p.obj[front], p.source[front], p.cluster[front], len(scene.faces),
                            None if adapted is None else adapted["extra"])
    books.choices.insert(0, Choice("mesh", mesh.mesh_note(size, auto[1] if auto else None, table, adapted)))
    p.pool()  # clustered patches share one B (their estimate was read so: noise.py)
    sections: dict = {"mesh": {"element_size_m": size, "automatic": auto is not None, "elements": len(p),
                               "units": p.units, "objects": table,
                               "refined": None if adapted is None else
                               {k: adapted[k] for k in ("split", "added", "levels", "points", "rays", "seconds",
                                                        "skipped") if k in adapted}}}
    outputs = {} if out is None else write_outputs(Path(out), scene, books.patches, width, height, sections,
                                                   float(settings.get("workplane_m") or 0.0), tracer=tracer,
                                                   views=views, painter=painter)
    if "luminaires" not in sections:  # without outputs: no work plane, the luminaires' figures only
        lums = luminaires.report_section(books.patches)
        if lums is not None:
            sections["luminaires"] = lums
    gltf_lights = punctual.report_section(books.patches.sources)
    if gltf_lights is not None:
        sections["gltf_lights"] = gltf_lights
    books.timings["outputs_s"] = time.perf_counter() - t0
    timings = {k: float(books.timings.get(k, 0.0)) for k in TIMINGS} | books.timings
    report = run_report(scene, books, settings, timings, warnings, outputs)
    report["divided"] = books.divided
    report["channels"], report["stiffness"] = books.channels, books.stiffness()
    report.update(sections)
    report.update(extra or {})
    if out is not None:
        write_json(Path(out) / "report.json", report)
    return report


class _DividedView:
    """What the progress bar reads, for a divided run."""

    def __init__(self, run):
        last = run.snapshots[-1]
        self._last = last
        self._estimate = run.estimate
        self.stats = Stats(shots=last.shots, rays=last.rays, barriers=run.barriers)

    def residual(self):
        return self._last.residual

    def estimate(self):
        return self._estimate

    def elapsed(self):
        return self._last.time

    def eta(self):
        return float("nan")


def solve_to(
    path,
    out: Path,
    config: SolverConfig | None = None,
    patch_size: float | None = None,
    scale: float = 1.0,
    on_progress=None,
    should_stop=None,
    width: int = 640,
    height: int = 480,
    divide=None,
    planes=None,
    up: str | None = None,
    two_sided: bool = False,
    workplane: float = 0.0,
    loaded: tuple | None = None,
    luminaires_path: str | os.PathLike | None = None,
    on_meshed=None,
    daylight=None,
) -> dict:
    """Load, solve and write everything to ``out``; return the report dict.

    ``divide`` (a DivideConfig) with more than one subscene solves divided, in
    process; one subscene (the default) uses the plain solver: no partition, no twins.
    ``up``, ``two_sided``, ``workplane``: scene settings (see scene_settings).  ``loaded``: see prepare.
    ``luminaires_path``: a luminaire schedule (luminaires.load_schedule) lighting the scene too.
    ``daylight``: a sky.DaylightSpec (``--sky``) lighting it from outside.
    ``on_meshed()``: told once the scene is loaded and meshed, as the solve starts (the CLI's stop
    handler: before it, a stop ends the command; after it, the solve stops and writes its results).
    """
    config = config or SolverConfig()
    out = Path(out)
    t0 = time.perf_counter()
    phases: dict = {}
    scene, patches, size = prepare(path, patch_size, scale, up, two_sided, timings=phases, loaded=loaded,
                                   workplane=workplane, sources=light_sources(luminaires_path, daylight, scale))
    t_load = time.perf_counter() - t0 + (loaded[1] if loaded is not None else 0.0)
    if on_meshed is not None:
        on_meshed()

    hooks = RunHooks(should_stop=should_stop, on_batch=on_progress)
    timings = {"load_and_mesh_s": t_load, **phases}
    strategy: Single | Divided
    if divide is not None and divide.subscenes > 1:
        if on_progress is not None:
            hooks.on_barrier = lambda run: on_progress(_DividedView(run))
        strategy = Divided(divide, planes=scene.planes_to_internal(planes))
    else:
        strategy = Single(divide)
    books = strategy.run(patches, config, hooks, timings)

    # the settings as run: automatic ones (ray density, tol) resolved (accuracy.resolve)
    report = finish_run(out, scene, books, scene_settings(scene, size, scale, two_sided, workplane), width, height,
                        tracer=strategy.tracer if isinstance(strategy, Single) else None)
    for w in report["warnings"]:
        log.warning(w)
    return report
