"""The demo catalogue's size charts: each demo garment in the letter sizes XS-XL of EN 13402-3
(pure data, no web, queue or storage imports; provenance in
``service/data/catalogue/PROVENANCE.md``, "Size charts").

* **Tops** (``top``) and **whole-body garments** (``suit``: the business suit, the dungarees):
  chest girth (men) or bust girth (women), the middles of the standard's letter-code intervals
  (``sizing.EN13402_3_LETTER_CHEST_CM``). The standard gives one scale for both; the charts
  are named per gender because each size's body is made for the garment's gender.
* **Bottoms** (``bottom``): waist girth, the middles of the standard's letter-code intervals
  (``sizing.EN13402_3_LETTER_WAIST_CM``), and hip girth, **derived** (not the standard's): the
  hip girth of the service's population-estimated avatar at that waist and gender
  (``shape.avatar_from_measurements`` with the waist alone, body model ``bm-5b35f84f21e1``),
  rounded to the centimetre (:data:`DERIVED_HIP_CM`).
* Shoes, the hat and the base layer (``underwear``) stay one size (no chart).

Each demo garment is shipped in the size nearest the body it is bound to (the mean example
avatar, measured for the garment's gender: ``sizing.nearest_size``) and graded to the others.
"""
from __future__ import annotations

from service.model.garments.sizing import EN13402_3_LETTER_CHEST_CM, EN13402_3_LETTER_WAIST_CM

DEMO_SIZE_LABELS = ("XS", "S", "M", "L", "XL")
STANDARD = "EN 13402-3:2013 letter codes"
# hip girth (cm) at each size's waist (XS..XL), per gender: derived from the body model (see the
# module docstring), not given by the standard's letter codes
DERIVED_HIP_CM: dict[str, tuple[float, ...]] = {
    "female": (90.0, 94.0, 98.0, 102.0, 106.0),
    "male": (85.0, 89.0, 92.0, 96.0, 100.0),
}
# the chart kind of each catalogue category (absent: one size)
CHART_KIND = {"top": "tops", "suit": "tops", "bottom": "bottoms"}


def _middle(interval: tuple[float, float]) -> float:
    return (interval[0] + interval[1]) / 2


def demo_chart(category: str, gender: str) -> tuple[str, dict[str, dict[str, float]]] | None:
    """(the chart's name, the chart: label -> measurements cm, XS..XL) of a demo garment of
    ``category`` and ``gender`` (female, male, unisex); None for a one-size garment."""
    kind = CHART_KIND.get(category)
    if kind is None:
        return None
    if kind == "tops":
        who = {"female": "women's tops (bust girth)", "male": "men's tops (chest girth)"}.get(
            gender, "tops (chest girth)")
        return (f"{STANDARD}, {who}",
                {lb: {"chest_cm": _middle(EN13402_3_LETTER_CHEST_CM[lb])} for lb in DEMO_SIZE_LABELS})
    hips = DERIVED_HIP_CM["female" if gender == "female" else "male"]
    who = "women's" if gender == "female" else "men's"
    return (f"{STANDARD}, {who} bottoms (waist girth; hip derived)",
            {lb: {"waist_cm": _middle(EN13402_3_LETTER_WAIST_CM[lb]), "hip_cm": hips[i]}
             for i, lb in enumerate(DEMO_SIZE_LABELS)})
