"""Which way a source file's spatial codes read: measured against the posed meshes, never assumed.

The platform's codes (DESIGN §3) say ``spatial[i, j]`` = "i is <code> of j" with right = +x, front = +z,
above = +y. A source file with the same vocabulary may mean the opposite: its matrix may be "j is <code>
of i" (**transposed**), or its right or front may be the other way (a left-handed engine, a mirrored
export: **x_mirrored**, **z_mirrored**). :data:`READINGS` lists the readings; :func:`read_as` turns the
file's codes into the platform's convention under one of them.

On import, every room's file codes are compared with the platform's codes of its posed meshes
(:func:`spread.relations.scene_spatial_codes`) under each reading (:func:`reading_counts`: equal pairs and
pairs, off the diagonal, where the file has a code); the counts are summed over the dataset and
:func:`choose_reading` picks the reading the data supports (``relations.convention=auto``), or checks the
one the user named. When the best reading agrees on fewer than ``relations.min_agreement`` of the pairs
the import is refused with a message naming the option (:class:`ConventionError`). Readings that agree
equally (a room with no front/behind pairs cannot tell z_mirrored from as_stored) are resolved in the
order of :data:`READINGS` and listed as ties.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spread.scene import SPATIAL_BEHIND, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF

READINGS = ("as_stored", "transposed", "x_mirrored", "z_mirrored")
_SWAP = {"x_mirrored": (SPATIAL_RIGHT, SPATIAL_LEFT), "z_mirrored": (SPATIAL_FRONT, SPATIAL_BEHIND)}


class ConventionError(ValueError):
    """No reading of the file's spatial codes agrees with the posed meshes (the message names the option)."""


@dataclass
class RelationsOptions:
    """``relations.*`` of ``spread-import``. convention: ``auto`` (the reading the data supports) or one of
    :data:`READINGS` (checked, and refused below ``min_agreement`` unless ``min_agreement=0``);
    min_agreement: the share of file pairs (off the diagonal) whose code, read that way, must equal the
    platform's code of the posed meshes."""

    convention: str = "auto"
    min_agreement: float = 0.9

    def check(self) -> None:
        if self.convention != "auto" and self.convention not in READINGS:
            raise ValueError(f"relations.convention={self.convention!r}: expected auto or one of {', '.join(READINGS)}")
        if not 0.0 <= float(self.min_agreement) <= 1.0:
            raise ValueError(f"relations.min_agreement={self.min_agreement}: expected a share in [0, 1]")


def read_as(codes: np.ndarray, reading: str) -> np.ndarray:
    """The file's (N, N) codes in the platform's convention under ``reading`` (entries < 0, "unknown", and
    the diagonal stay as they are)."""
    codes = np.asarray(codes)
    if reading == "as_stored":
        return codes.copy()
    if reading == "transposed":
        out = codes.T.copy()
        np.fill_diagonal(out, np.diag(codes))
        return out
    if reading in _SWAP:
        a, b = _SWAP[reading]
        out = codes.copy()
        out[codes == a], out[codes == b] = b, a
        return out
    raise ValueError(f"unknown reading {reading!r} (known: {', '.join(READINGS)})")


def reading_counts(file_codes: np.ndarray, platform_codes: np.ndarray) -> dict:
    """``{reading: [equal, pairs]}``: off-diagonal pairs where the file, read that way, has a code (≥ 0, not
    self) and how many of them equal the platform's code."""
    off = ~np.eye(len(file_codes), dtype=bool)
    out = {}
    for reading in READINGS:
        read = read_as(file_codes, reading)
        known = off & (read >= 0) & (read != SPATIAL_SELF)
        out[reading] = [int(((read == platform_codes) & known).sum()), int(known.sum())]
    return out


def add_counts(total: dict, counts: dict | None) -> dict:
    for reading, (equal, pairs) in (counts or {}).items():
        cur = total.setdefault(reading, [0, 0])
        cur[0] += equal
        cur[1] += pairs
    return total


def choose_reading(totals: dict, options: RelationsOptions) -> dict:
    """The reading to use, from counts summed over the dataset: ``{"reading", "agreement" (per reading),
    "ties", "chosen_by", "message"}``; raises :class:`ConventionError` when it agrees too little."""
    options.check()
    agreement = {r: (totals[r][0] / totals[r][1] if totals.get(r) and totals[r][1] else None) for r in READINGS}
    pairs = max((totals[r][1] for r in READINGS if r in totals), default=0)
    if pairs == 0:
        reading = "as_stored" if options.convention == "auto" else options.convention
        return {"reading": reading, "agreement": agreement, "pairs": 0, "ties": [], "chosen_by": "no file codes",
                "message": "relations: the files carry no spatial codes to measure; nothing to read"}
    if options.convention == "auto":
        best = max(agreement[r] for r in READINGS)
        ties = [r for r in READINGS if agreement[r] == best]
        reading, chosen_by = ties[0], "auto: the reading the data supports"
    else:
        reading, chosen_by = options.convention, "relations.convention (set by the user)"
        ties = [r for r in READINGS if agreement[r] == agreement[reading]]
    table = ", ".join(f"{r} {agreement[r]:.3f}" for r in READINGS)
    if agreement[reading] < float(options.min_agreement):
        raise ConventionError(
            f"relations: no reading of the files' spatial codes agrees with the posed meshes (agreement over "
            f"{pairs} pairs: {table}; needed {options.min_agreement:g}). The codes may follow another rule or be "
            f"wrong; to import anyway name a reading, relations.convention=<{'|'.join(READINGS)}>, with "
            f"relations.min_agreement=0")
    message = (f"relations: reading the files' spatial codes {reading} ({chosen_by}); agreement with the posed "
               f"meshes over {pairs} pairs: {table}")
    if len(ties) > 1:
        message += f" (the data cannot tell {', '.join(ties)} apart)"
    return {"reading": reading, "agreement": agreement, "pairs": pairs, "ties": ties, "chosen_by": chosen_by,
            "message": message}
