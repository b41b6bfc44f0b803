"""The synthetic animal's coats: the colours of its materials and the fur patterns.

Every body part has a material (:data:`MATERIALS`); a coat gives each material a primary
and a secondary colour (:func:`coat_palette`), and :func:`fur_pattern` says where on a
part the secondary colour shows: the hooded rat's dark back stripe and head, the piebald
rat's irregular patches (material ``"patched"``, given to every furry part of a piebald
animal by :func:`freipose.synth.body.build_body`).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from freipose.synth.look import value_noise3

MATERIALS = (
    "haunch", "chest", "head", "snout", "nose", "eye", "ear", "limb", "paw", "tail", "patched",
)  # fmt: skip
MAT: Mapping[str, int] = MappingProxyType({n: i for i, n in enumerate(MATERIALS)})
#: the materials with fur (a fine fur texture; the others are skin)
FURRY = tuple(MAT[m] for m in ("haunch", "chest", "head", "snout", "limb", "patched"))


def coat_palette(appearance: str, tint: tuple[float, float, float]) -> np.ndarray:
    """(n_materials, 2, 3) BGR albedo in [0, 1]: [primary, secondary] per material.

    Args:
        appearance: the coat (``freipose.synth.body.COATS``).
        tint: (3,) BGR multiplier on the fur colour.
    """
    white = np.array([0.86, 0.9, 0.93]) * np.array(tint)
    pink = np.array([0.62, 0.64, 0.9])
    black = np.array([0.07, 0.075, 0.085]) * np.array(tint)
    cols: dict[str, tuple[np.ndarray, ...]] = {"patched": (white, black)}
    if appearance == "hooded":
        dark = np.array([0.08, 0.085, 0.1])
        cols |= {
            "haunch": (white, dark), "chest": (white, dark), "head": (dark, dark),
            "snout": (dark, dark), "nose": (np.array([0.3, 0.3, 0.42]),) * 2,
            "eye": (np.array([0.02, 0.02, 0.02]),) * 2,
            "ear": (np.array([0.36, 0.37, 0.5]),) * 2, "limb": (white, white),
            "paw": (pink, pink), "tail": (np.array([0.45, 0.48, 0.58]),) * 2,
        }  # fmt: skip
    elif appearance == "dark":
        skin = np.array([0.33, 0.34, 0.42])
        cols |= {
            "haunch": (black, black), "chest": (black, black), "head": (black, black),
            "snout": (black, black), "nose": (skin,) * 2,
            "eye": (np.array([0.02, 0.02, 0.02]),) * 2, "ear": (skin * 0.8,) * 2,
            "limb": (black, black), "paw": (skin,) * 2, "tail": (skin * 0.75,) * 2,
        }  # fmt: skip
    elif appearance == "piebald":  # its furry parts are "patched"
        grey = np.array([0.4, 0.42, 0.5])
        cols |= {m: (white, black) for m in ("haunch", "chest", "head", "snout", "limb")}
        cols |= {
            "nose": (pink * 0.9,) * 2, "eye": (np.array([0.03, 0.03, 0.03]),) * 2,
            "ear": (grey,) * 2, "paw": (pink,) * 2, "tail": (grey * 1.1,) * 2,
        }  # fmt: skip
    else:
        white = white * np.array([0.93, 1.0, 1.02])  # slightly creamy
        cols |= {
            "haunch": (white, white), "chest": (white, white), "head": (white, white),
            "snout": (white, white), "nose": (pink * 0.95,) * 2,
            "eye": (np.array([0.12, 0.1, 0.75]),) * 2, "ear": (pink,) * 2,
            "limb": (white, white), "paw": (pink,) * 2, "tail": (pink * 0.97,) * 2,
        }  # fmt: skip
    return np.array([np.stack(cols[m]) for m in MATERIALS])


def fur_pattern(
    mats: np.ndarray, ids: np.ndarray, p: np.ndarray, q: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """(m,) bool: the surface points that show their material's secondary colour.

    Args:
        mats: (m,) material of each point.
        ids: (m,) part id of each point.
        p: (m, 3) the points on their part's unit sphere (x forward, z up).
        q: (m, 3) the points in the part's local frame, mm (the pattern moves with it).
        noise: the renderer's value-noise table (``freipose.synth.look``).
    """
    second = np.zeros(len(ids), bool)
    wob = 0.12 * value_noise3(noise, q / 12.0 + 7.1)
    hm = mats == MAT["haunch"]
    second[hm] = (p[hm, 2] + wob[hm] > 0.8) & (np.abs(p[hm, 1]) < 0.45)
    cm = mats == MAT["chest"]
    second[cm] = ((p[cm, 2] + wob[cm] > 0.78) & (np.abs(p[cm, 1]) < 0.5)) | (
        (p[cm, 0] + wob[cm] > 0.4) & (p[cm, 2] > -0.4)
    )
    pm = mats == MAT["patched"]  # irregular patches of about 2 cm, each part its own
    if pm.any():
        spot = q[pm] / 20.0 + ids[pm, None] * np.float32(5.3) + np.float32(2.9)
        second[pm] = value_noise3(noise, spot) > 0.0
    return second
