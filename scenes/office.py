"""One storey of an office building: a grid of rooms joined by doors.

Layout (metres, +Y up).  Rooms form ``rows`` x ``cols`` grid; row ``i`` runs
along +Z, column ``j`` along +X.  Every room's free floor is exactly
``room`` x ``room``; interior walls of thickness ``wall`` separate them, so
room (i, j) covers ``x in [j p, j p + room]``, ``z in [i p, i p + room]`` with
pitch ``p = room + wall`` (see :func:`room_rect`), and the building spans
``[0, cols p - wall] x [0, height] x [0, rows p - wall]``.

Surfaces: per room one floor quad ``room_i_j_floor`` (+Y) and one ceiling
quad ``room_i_j_ceiling`` (-Y) covering exactly its free ``room`` x ``room``
area, plus a floor strip ``door_h_i_j_floor`` / ``door_v_i_j_floor`` under each
doorway (door width x wall thickness, between the jambs; the ceiling there is
the lintel's underside).  Nothing lies under or over a wall, so no floor or
ceiling patch straddles two rooms (edges of adjacent pieces meet exactly; the
door strips form T-junctions with the room floors, without gaps).  Outer walls
are single-sided quads facing in, one per room side (``outer_south_j`` at
z = 0, ``outer_north_j``, ``outer_west_i`` at x = 0, ``outer_east_i``);
interior walls are boxes with their faces outward, minus the faces hidden
against floor, ceiling, outer walls and wall junctions:
``wall_h_i_j`` (along X, between rooms (i-1, j) and (i, j)) and ``wall_v_i_j``
(along Z, between (i, j-1) and (i, j)).  Each has one door (gap from the floor
to ``door_height``, jambs, and a ``lintel_*`` above) at a seeded random
position, so all rooms connect.  The enclosure is closed: from any point
inside a room, every ray hits a front face.

Lights ``light_i_j_k``: 0.6 x 1.2 m emissive quads 1 cm below the ceiling,
facing down, on a grid (4 in a 4 m room), in ``max(1, ceil(lit_fraction *
rooms))`` seeded random rooms.  Furniture ``desk_i_j_k`` / ``cabinet_i_j_k``:
1-3 boxes per room (fewer only if a small room has no space left) standing on
the floor (no bottom face), >= 0.1 m from walls and each other, never within
1 m in front of a door.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from .objwriter import ObjWriter

__all__ = ["office_floor", "room_rect", "LIGHT_EXITANCE"]

#: Default ceiling-light exitance, W/m^2 (slightly warm white).
LIGHT_EXITANCE = (10.0, 9.6, 8.8)
_DOOR_MARGIN = 0.3  # m, minimum distance from a door to the wall's end
_CLEAR = 1.0  # m, furniture-free depth in front of a door
_GAP = 0.1  # m, furniture clearance from walls and other furniture
_FURNITURE = {  # kind: (width range, depth range, height range) in metres
    "desk": ((1.2, 1.6), (0.7, 0.8), (0.72, 0.76)),
    "cabinet": ((0.5, 0.9), (0.4, 0.5), (1.1, 1.9)),
}
_FURNITURE_KD = {
    "desk": [(0.55, 0.40, 0.25), (0.45, 0.32, 0.22), (0.50, 0.50, 0.48)],
    "cabinet": [(0.45, 0.45, 0.48), (0.25, 0.30, 0.45), (0.55, 0.22, 0.20)],
}


def room_rect(i: int, j: int, room: float = 4.0, wall: float = 0.12) -> tuple[float, float, float, float]:
    """Free floor of room (row i, column j) as ``(x0, z0, x1, z1)`` in metres."""
    p = room + wall
    return (j * p, i * p, j * p + room, i * p + room)


def _p(along: int, a: float, y: float, b: float) -> tuple:
    """Point from a coordinate ``a`` on horizontal axis ``along`` (0 = x, 2 = z),
    ``b`` on the other horizontal axis, and height ``y``."""
    return (a, y, b) if along == 0 else (b, y, a)


def _rect(w, along, a0, a1, y0, y1, b, facing_b):
    """Vertical rectangle spanning a0..a1 along ``along`` at ``b``, facing +-b."""
    n = np.array(_p(along, 0.0, 0.0, float(facing_b)))
    w.add_quad(_p(along, a0, y0, b), _p(along, a1, y0, b), _p(along, a1, y1, b), _p(along, a0, y1, b), facing=n)


def _wall(w, name, along, s, t, door, height, door_height):
    """Interior wall segment: ``s`` = (s0, s1) extent along ``along``, ``t`` =
    (t0, t1) thickness on the other axis, ``door`` = (d0, d1) gap."""
    (s0, s1), (t0, t1), (d0, d1) = s, t, door
    w.begin(f"wall_{name}", "wall")
    for b, f in ((t0, -1), (t1, 1)):
        _rect(w, along, s0, d0, 0.0, height, b, f)
        _rect(w, along, d1, s1, 0.0, height, b, f)
    for a, f in ((d0, 1.0), (d1, -1.0)):  # jambs, facing into the opening
        n = _p(along, f, 0.0, 0.0)
        w.add_quad(_p(along, a, 0, t0), _p(along, a, 0, t1), _p(along, a, door_height, t1),
                   _p(along, a, door_height, t0), facing=n)
    w.begin(f"lintel_{name}", "wall")
    for b, f in ((t0, -1), (t1, 1)):
        _rect(w, along, d0, d1, door_height, height, b, f)
    w.add_quad(_p(along, d0, door_height, t0), _p(along, d1, door_height, t0),
               _p(along, d1, door_height, t1), _p(along, d0, door_height, t1), facing=(0, -1, 0))


def _overlaps(box, others, gap=0.0) -> bool:
    x0, z0, x1, z1 = box
    return any(x0 < b[2] + gap and b[0] < x1 + gap and z0 < b[3] + gap and b[1] < z1 + gap for b in others)


def office_floor(
    folder,
    rows: int = 2,
    cols: int = 3,
    room: float = 4.0,
    height: float = 2.8,
    wall: float = 0.12,
    door_width: float = 0.9,
    door_height: float = 2.1,
    lit_fraction: float = 0.5,
    seed: int = 0,
    light_exitance=LIGHT_EXITANCE,
    stem: str = "office",
) -> pathlib.Path:
    """Write the office floor as ``<folder>/<stem>.obj`` + ``.mtl``; return the OBJ path.

    Lengths in metres, ``light_exitance`` in W/m^2 (scalar or RGB).  ``seed``
    fixes door positions, lit rooms and furniture: same arguments give
    byte-identical files.  Layout and naming: see the module docstring.
    """
    if rows < 1 or cols < 1:
        raise ValueError("need at least one room")
    if not 0 < wall < room or room < door_width + 2 * _DOOR_MARGIN:
        raise ValueError(f"room {room} too small for wall {wall} / door width {door_width}")
    if not 0 < door_height < height or height <= 2.2:
        raise ValueError(f"need 0 < door_height < height and height > 2.2 (got {door_height}, {height})")
    if not 0 <= lit_fraction <= 1:
        raise ValueError(f"lit_fraction {lit_fraction} must be in [0, 1]")
    rng = np.random.default_rng(seed)
    p = room + wall
    width, depth = cols * p - wall, rows * p - wall
    w = ObjWriter()
    w.material("floor", (0.32, 0.30, 0.27))
    w.material("wall", (0.70, 0.70, 0.68))
    w.material("ceiling", (0.80, 0.80, 0.80))
    w.material("light", (0.80, 0.80, 0.80), ke=light_exitance)

    for i in range(rows):  # floor and ceiling per room, never under/over a wall
        for j in range(cols):
            x0, z0, x1, z1 = room_rect(i, j, room, wall)
            w.begin(f"room_{i}_{j}_floor", "floor")
            w.add_rect(1, 0.0, (x0, z0), (x1, z1), 1)
            w.begin(f"room_{i}_{j}_ceiling", "ceiling")
            w.add_rect(1, height, (x0, z0), (x1, z1), -1)
    for j in range(cols):
        x0, _, x1, _ = room_rect(0, j, room, wall)
        w.begin(f"outer_south_{j}", "wall")
        w.add_rect(2, 0.0, (x0, 0.0), (x1, height), 1)
        w.begin(f"outer_north_{j}", "wall")
        w.add_rect(2, depth, (x0, 0.0), (x1, height), -1)
    for i in range(rows):
        _, z0, _, z1 = room_rect(i, 0, room, wall)
        w.begin(f"outer_west_{i}", "wall")
        w.add_rect(0, 0.0, (0.0, z0), (height, z1), 1)
        w.begin(f"outer_east_{i}", "wall")
        w.add_rect(0, width, (0.0, z0), (height, z1), -1)

    # interior walls with one door each; remember the furniture-free zones
    keep_out = []
    segments = [("h", i, j, 0) for i in range(1, rows) for j in range(cols)]
    segments += [("v", i, j, 2) for i in range(rows) for j in range(1, cols)]
    for kind, i, j, along in segments:
        x0, z0, x1, z1 = room_rect(i, j, room, wall)
        s = (x0, x1) if along == 0 else (z0, z1)
        t = (z0 - wall, z0) if along == 0 else (x0 - wall, x0)
        lo = s[0] + _DOOR_MARGIN + 0.5 * door_width
        c = round(float(rng.uniform(lo, s[1] - (lo - s[0]))), 2)
        door = (c - 0.5 * door_width, c + 0.5 * door_width)
        _wall(w, f"{kind}_{i}_{j}", along, s, t, door, height, door_height)
        w.begin(f"door_{kind}_{i}_{j}_floor", "floor")  # floor of the doorway, jamb to jamb
        f0, f1 = _p(along, door[0], 0.0, t[0]), _p(along, door[1], 0.0, t[1])
        w.add_rect(1, 0.0, (f0[0], f0[2]), (f1[0], f1[2]), 1)
        a = (door[0] - 0.2, door[1] + 0.2)
        b = (t[0] - _CLEAR, t[1] + _CLEAR)
        keep_out.append((a[0], b[0], a[1], b[1]) if along == 0 else (b[0], a[0], b[1], a[1]))

    # ceiling lights in a random subset of rooms
    n_rooms = rows * cols
    n_lit = max(1, math.ceil(lit_fraction * n_rooms))
    lit = sorted(int(k) for k in rng.choice(n_rooms, size=n_lit, replace=False))
    n = max(1, round(room / 2.0))
    cell = room / n
    lx, lz = min(0.6, 0.8 * cell), min(1.2, 0.8 * cell)
    for k in lit:
        i, j = divmod(k, cols)
        x0, z0, _, _ = room_rect(i, j, room, wall)
        for m, (u, v) in enumerate((u, v) for u in range(n) for v in range(n)):
            cx, cz = x0 + (u + 0.5) * cell, z0 + (v + 0.5) * cell
            w.begin(f"light_{i}_{j}_{m}", "light")
            w.add_rect(1, height - 0.01, (cx - lx / 2, cz - lz / 2), (cx + lx / 2, cz + lz / 2), -1)

    # furniture: 1-3 boxes per room, rejection-sampled
    for i in range(rows):
        for j in range(cols):
            x0, z0, x1, z1 = room_rect(i, j, room, wall)
            # a piece lies inside its room: only keep-out boxes reaching into the room can touch it
            # (the whole floor's list made the 20x20 office's writing 2.6 s)
            near = [b for b in keep_out if b[2] > x0 and b[0] < x1 and b[3] > z0 and b[1] < z1]
            placed: list[tuple[float, float, float, float]] = []
            for k in range(int(rng.integers(1, 4))):
                kind = "desk" if k == 0 or rng.random() < 0.4 else "cabinet"
                (wa, wb), (da, db), (ha, hb) = _FURNITURE[kind]
                fw, fd = round(rng.uniform(wa, wb), 2), round(rng.uniform(da, db), 2)
                fh = round(min(rng.uniform(ha, hb), height - 0.5), 2)
                if rng.random() < 0.5:
                    fw, fd = fd, fw
                for _ in range(200):
                    bx = round(rng.uniform(x0 + _GAP, x1 - _GAP - fw), 2)
                    bz = round(rng.uniform(z0 + _GAP, z1 - _GAP - fd), 2)
                    box = (bx, bz, bx + fw, bz + fd)
                    inside = box[0] >= x0 + 0.05 and box[1] >= z0 + 0.05
                    if inside and box[2] <= x1 - 0.05 and box[3] <= z1 - 0.05 and not (
                        _overlaps(box, near) or _overlaps(box, placed, _GAP)
                    ):
                        break
                else:
                    continue  # no room left for this piece
                placed.append(box)
                palette = _FURNITURE_KD[kind]
                shade = int(rng.integers(len(palette)))
                mat = w.material(f"{kind}_{shade}", palette[shade])
                w.begin(f"{kind}_{i}_{j}_{len(placed) - 1}", mat)
                w.add_box((box[0], 0.0, box[1]), (box[2], fh, box[3]), outward=True, skip_faces=("bottom",))
    return w.write(folder, stem)
