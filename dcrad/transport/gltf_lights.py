"""What glTF's light extensions share (``KHR_lights_punctual`` in punctual.py, ``EXT_lights_ies`` in
luminaires.py): the extension's list of lights, the nodes that place them, and one name each."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from dcrad.errors import SceneFormatError

__all__ = ["extension_lights", "placements", "unique_name"]


def extension_lights(header: dict, path: str, extension: str) -> list:
    """The top-level ``extensions.<extension>.lights`` list ([] without it); SceneFormatError naming
    ``path`` when it is not a list."""
    ext = header.get("extensions")
    ext = ext.get(extension) if isinstance(ext, dict) else None
    lights = ext.get("lights", []) if isinstance(ext, dict) else []
    if not isinstance(lights, list):
        raise SceneFormatError(f"{path}: {extension}'s 'lights' is not a list")
    return lights


def placements(nodes: Iterable, path: str, extension: str, count: int) -> Iterator[tuple]:
    """(node name, light index, the node's reference, world 4x4) of each node placing one of the
    ``count`` lights of ``extension``; SceneFormatError naming ``path`` and the node for an index
    the file lacks.  ``nodes``: (index, node, world 4x4) of the default scene's nodes."""
    for i, node, world in nodes:
        ref = node.get("extensions", {}).get(extension) if isinstance(node.get("extensions"), dict) else None
        if ref is None:
            continue
        node_name = node.get("name") or f"node {i}"
        index = ref.get("light") if isinstance(ref, dict) else None
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < count:
            raise SceneFormatError(f"{path}: node '{node_name}' refers to {extension} light {index!r}, but the file "
                                   f"has {count} light(s)")
        yield node_name, index, ref, world


def unique_name(base: str, taken: set[str]) -> str:
    """``base``, or ``base #2``, ``#3``... when a light placed by several nodes already took it (one
    source each); the name is added to ``taken``."""
    name, k = base, 2
    while name in taken:
        name = f"{base} #{k}"
        k += 1
    taken.add(name)
    return name
