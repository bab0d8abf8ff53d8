"""What a run chose and why: report.json's ``choices``, entries with a code and a sentence.

The sentence is for people; the code is for code.  Passes, shared runs and the final gather
replace or relabel earlier entries (a second pass's direct light, a later gather round), and
they find them by code, never by the wording of the sentence.

Codes (stable; the report's readers may rely on them):

==================  ==============================================================
``workers``         how many worker processes, and why (the default's choice)
``strategy``        how the coordinator runs the job (shared or divided), and why
``mesh``            the element size and what became of the input triangles
``clusters``        clusters kept and undone after the solve
``grey``            one colour channel solved, not three
``direct``          whether the direct light was gathered or shot, and how
``plan``            the accuracy plan (shoot coarsely, gather at the end)
``density``         a first pass that shoots its light at a share of the density, to measure the noise
``budget``          how a ray budget or time limit cut the plan
``final_gather``    the final gather of the indirect light
``pass``            an earlier accuracy pass (its own ``direct`` entries relabelled)
``passes``          the accuracy passes blended, and why
``accuracy``        the stop rule and the ray density
``noise_floor``     the run ended on its noise floor, and what would lower it
``stiff``           overshooting in a stiff scene
``subscenes``       partition, boundaries and twin buffers of the run
``barriers``        barriers aimed at the target
``shared``          how a shared run split its work
``unused_flags``    flags given that do not apply to the run as it ran
``resumed``         a job resumed after a coordinator restart
==================  ==============================================================
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

__all__ = ["Choice", "Choices", "CODES"]

CODES = ("workers", "strategy", "mesh", "clusters", "grey", "direct", "plan", "density", "budget", "final_gather",
         "pass", "passes", "accuracy", "noise_floor", "stiff", "subscenes", "barriers", "shared", "unused_flags",
         "resumed")


@dataclass(frozen=True)
class Choice:
    code: str  #: one of CODES
    text: str  #: the sentence the report shows

    def __post_init__(self) -> None:
        if self.code not in CODES:
            raise ValueError(f"choice code {self.code!r} is not one of {', '.join(CODES)}")

    def as_dict(self) -> dict:
        return {"code": self.code, "text": self.text}

    @staticmethod
    def from_dict(d: dict) -> "Choice":
        return Choice(str(d["code"]), str(d["text"]))


class Choices(list):
    """A run's choices in the order they were made (a list of Choice, nothing else: a sentence
    without a code is refused where it is added, not found missing by a later reader)."""

    def __init__(self, items: Iterable[Choice] = ()) -> None:
        super().__init__(_checked(c) for c in items)

    def append(self, item: Choice) -> None:
        super().append(_checked(item))

    def insert(self, index, item: Choice) -> None:
        super().insert(index, _checked(item))

    def extend(self, items: Iterable[Choice]) -> None:
        super().extend(_checked(c) for c in items)

    def add(self, code: str, text: str) -> None:
        self.append(Choice(code, text))

    def drop(self, *codes: str) -> None:
        """Remove every entry of these codes (in place)."""
        self[:] = [c for c in self if c.code not in codes]

    def set(self, code: str, text: str) -> None:
        """The one entry of ``code``, replacing any before it."""
        self.drop(code)
        self.add(code, text)

    def of(self, *codes: str) -> list[Choice]:
        return [c for c in self if c.code in codes]

    def texts(self) -> list[str]:
        return [c.text for c in self]

    def as_json(self) -> list[dict]:
        return [c.as_dict() for c in self]

    @staticmethod
    def from_json(items: Iterable[dict]) -> "Choices":
        return Choices(Choice.from_dict(d) for d in items)


def _checked(item) -> Choice:
    if not isinstance(item, Choice):
        raise TypeError(f"a choice needs a code and a sentence (choices.Choice), not {item!r:.80}")
    return item
