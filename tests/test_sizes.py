"""Sizes and fit, the maths (``service.model.sizing``): chart validation, grading keeps the base
size and grows the others, garment girths per region, verdict thresholds per fabric, the
recommendation rule and monotonicity of ease and strain with size."""
from __future__ import annotations

import numpy as np
import pytest

from service.application.sizes import Chart, chart_bodies
from service.model.garments import sizing as S
from service.model.garments.catalogue import load_catalogue

CHART = {"S": {"chest_cm": 88.0, "waist_cm": 76.0, "hip_cm": 94.0},
         "M": {"chest_cm": 96.0, "waist_cm": 84.0, "hip_cm": 102.0},
         "L": {"chest_cm": 104.0, "waist_cm": 92.0, "hip_cm": 110.0}}


def test_validate_chart() -> None:
    sizes, base = S.validate_chart(CHART, None)
    assert [s["label"] for s in sizes] == ["S", "M", "L"] and base == "M"
    assert S.validate_chart(CHART, "L")[1] == "L"
    bad = [([], "JSON object"), ({"S": {"neck_cm": 38}}, "unknown measurement"),
           ({"S": {"chest_cm": True}}, "number"), ({"S": {"chest_cm": float("nan")}}, "finite"),
           ({"S": {"chest_cm": 90}, "M": {"chest_cm": 90}}, "increase"),
           ({"S": {"chest_cm": 90, "hip_cm": 96}, "M": {"chest_cm": 94, "hip_cm": 95}}, "increase"),
           ({"S": {"chest_cm": 90}, " s ": {"chest_cm": 94}}, "repeated"),
           ({"S,M": {"chest_cm": 90}}, "no comma"), ({"S": {}}, "object of measurement"),
           ({"S": {"chest_cm": 90}, "M": {"waist_cm": 80}}, "same measurements")]
    for chart, text in bad:
        with pytest.raises(S.ChartError, match=text):
            S.validate_chart(chart, None)
    with pytest.raises(S.ChartError, match="not a size"):
        S.validate_chart(CHART, "XL")
    with pytest.raises(S.ChartError, match="range"):
        S.validate_chart({"S": {"chest_cm": 20}}, None, {"chest_cm": (60.0, 160.0)})
    with pytest.raises(S.ChartError, match="woven, knit, stretch"):
        S.check_fabric("silk")
    with pytest.raises(S.ChartError, match="S, M, L"):
        S.size_index(["S", "M", "L"], "XL", 1)


@pytest.fixture(scope="module")
def graded(model):
    """The catalogue's pencil skirt and women's T-shirt graded S/M/L from the mean avatar."""
    chart = Chart(S.validate_chart(CHART, "M")[0], "M", "woven")
    bodies = chart_bodies(model, chart)
    out = {}
    for name in ("pencil-skirt", "womens-tshirt"):
        item = next(i for i in load_catalogue().garments() if i.id == name)
        src = np.asarray(model.mean, np.float64)
        g0 = item.binding.fit(src)
        faces = np.asarray(item.faces, np.int64)
        rests = S.grade(model, g0, faces, src, bodies, chart.base)
        on = S.size_bodies_on(src, bodies, chart.base)
        out[name] = (g0, faces, rests, on, bodies, chart)
    return out


def test_grading_keeps_the_base_size(graded) -> None:
    for g0, faces, rests, on, bodies, chart in graded.values():
        assert np.array_equal(rests[chart.base], np.asarray(g0, np.float32))
        assert np.array_equal(on[chart.base], np.asarray(on[chart.base]))
        assert not np.allclose(rests[0], rests[chart.base], atol=1e-3)


def test_grading_follows_the_chart(model, graded) -> None:
    """Each size's garment girths grow by about the chart's girth steps (8 cm per size here),
    and its ease on its own body stays the design ease (within 1.5 cm)."""
    for name, (g0, faces, rests, on, bodies, chart) in graded.items():
        fit = S.sized_garment_fit(model, rests, faces, on, chart.labels, chart.base, bodies[chart.base], "woven")
        present = np.isfinite(fit.design_cm)
        assert present.any(), name
        for s in range(3):
            own = S.girths_of_body(model, bodies[s])
            ease = fit.garment_cm[s] - own
            assert np.all(np.abs(ease - fit.design_cm)[present] < 1.5), (name, s, ease, fit.design_cm)
        steps = np.diff(fit.garment_cm, axis=0)
        assert np.all(steps[:, present] > 0.5), (name, steps)
        charted = present & np.isin(S.GIRTH_REGIONS, ["chest", "waist", "hip"])
        assert np.all(steps[:, charted] > 5.0), (name, steps)


def test_recommendation_and_monotonicity(model, graded) -> None:
    """Bodies made from each size's chart measurements get that size; on any body ease grows
    and strain falls with the size at every region."""
    for name, (g0, faces, rests, on, bodies, chart) in graded.items():
        fit = S.sized_garment_fit(model, rests, faces, on, chart.labels, chart.base, bodies[chart.base], "knit")
        for s in range(3):
            rep = S.fit_report(fit, S.girths_of_body(model, bodies[s]))
            assert rep.recommended == s, (name, s, rep.to_dict())
            E, T = rep.ease_cm[:, rep.present], rep.strain_pct[:, rep.present]
            assert np.all(np.diff(E, axis=0) > 0) and np.all(np.diff(T, axis=0) <= 0)


def test_verdicts_per_fabric() -> None:
    """The same ease is tight in a woven and fit in a knit; a design's own ease is fit."""
    body = np.array([100.0])
    design = np.array([6.0])
    v = lambda e, f: S.VERDICTS[int(S.verdicts(np.array([e]), body, design, f)[0])]  # noqa: E731
    assert v(1.0, "woven") == "tight" and v(1.0, "knit") == "fit"
    assert v(-1.5, "woven") == "too_tight" and v(-5.0, "knit") == "tight" and v(-5.0, "stretch") == "fit"
    assert v(3.0, "woven") == "fit"  # the design's 6 % less its 4 % margin: a woven is tight below 2 % here
    assert v(6.0, "woven") == "fit" and v(25.0, "woven") == "loose" and v(40.0, "woven") == "too_loose"
    # a loose design (18 % ease) is fit at its own ease, loose well beyond it
    assert S.VERDICTS[int(S.verdicts(np.array([18.0]), body, np.array([18.0]), "stretch")[0])] == "fit"


def test_recommend_rule() -> None:
    design = np.array([6.0, 6.0])
    ease = np.array([[0.0, 4.0], [5.0, 9.0], [12.0, 15.0]])
    verdict = np.array([[1, 2], [2, 2], [2, 3]])
    assert S.recommend(ease, design, verdict) == 1
    assert S.recommend(ease, design, np.ones_like(verdict)) == 2  # all tight: the loosest
    # the chart sizes the first region only: the distance is taken there
    ease = np.array([[4.0, 30.0], [7.0, 6.0], [12.0, 15.0]])
    verdict = np.full((3, 2), 2)
    assert S.recommend(ease, design, verdict) == 1 and S.recommend(ease, design, verdict, np.array([True, False])) == 1
    ease[0, 1] = 6.0
    ease[1, 1] = 30.0
    assert S.recommend(ease, design, verdict, np.array([True, False])) == 1
    assert S.recommend(ease, design, verdict) == 0


def test_girths_of_a_garment_that_has_no_region(model) -> None:
    """A skirt has a hip but no chest, upper arm or thigh (it goes around both legs)."""
    item = next(i for i in load_catalogue().garments() if i.id == "pencil-skirt")
    g = item.binding.fit(model.mean)
    G = S.garment_girths(S.GarmentSections(item.faces, len(g)), g, S.region_spec(model).regions(model.mean))
    got = {r for r, x in zip(S.GIRTH_REGIONS, G) if np.isfinite(x)}
    assert "hip" in got and not got & {"chest", "upper_arm", "thigh", "shoulders"}


def test_fit_map_colour_scales() -> None:
    """Strain: blue at rest, green half way, red at the fabric's limit (and beyond); ease: red
    at contact, green at the fabric's designed gap, blue where it hangs."""
    lim = S.FIT_THRESHOLDS["knit"].strain_limit_pct / 100
    c = S.strain_colors(np.array([0.0, lim / 2, lim, 2 * lim]), "knit").astype(int)
    assert c[0, 2] > 200 and c[0, 0] < 30  # blue
    assert c[1, 1] > 150 and c[1, 0] < 30 and c[1, 2] < 60  # green
    assert c[2, 0] == 255 and c[2, 1] == 0 and (c[3] == c[2]).all()  # red, saturated
    assert (c[:, 3] == 255).all()
    # the same strain is redder on a woven (it barely stretches) than on a stretch fabric
    w, st = S.strain_colors(np.array([0.02]), "woven")[0], S.strain_colors(np.array([0.02]), "stretch")[0]
    assert int(w[0]) > int(st[0])
    mid = S.fit_gap_m("woven")
    e = S.ease_colors(np.array([-0.01, S.EASE_MAP_CONTACT_M, mid, S.EASE_MAP_HANG_M, 0.2]), "woven").astype(int)
    assert e[0, 0] == 255 and e[1, 0] == 255 and e[1, 1] == 0  # red: pressing
    assert e[2, 1] > 150 and e[2, 0] < 30  # green at the designed gap
    assert e[3, 2] > 200 and (e[4] == e[3]).all()  # blue: hanging
    assert S.fit_gap_m("stretch") < S.fit_gap_m("knit") < S.fit_gap_m("woven")


def test_demo_charts(model) -> None:
    """Every demo garment's chart: tops and suits by chest (bust) girth, bottoms by waist (and
    the derived hip), the middles of the EN 13402-3 letter-code intervals XS-XL, valid charts
    in the model's ranges; shoes, the hat and underwear one size. The base size is the one
    nearest the body."""
    from service.model.garments.demo_sizes import DEMO_SIZE_LABELS, demo_chart

    ranges = {a.name: (a.min, a.max) for a in model.attributes if a.name != "gender"}
    seen = set()
    for item in load_catalogue().garments():
        found = demo_chart(item.category, item.gender)
        if item.category in ("shoes", "hat", "underwear"):
            assert found is None, item.id
            continue
        assert found is not None, item.id
        name, chart = found
        assert "EN 13402-3" in name and tuple(chart) == DEMO_SIZE_LABELS
        sizes, _ = S.validate_chart(chart, "M", ranges)
        key = "waist_cm" if item.category == "bottom" else "chest_cm"
        table = S.EN13402_3_LETTER_WAIST_CM if key == "waist_cm" else S.EN13402_3_LETTER_CHEST_CM
        for s in sizes:
            lo, hi = table[s["label"]]
            assert s["measurements"][key] == (lo + hi) / 2, (item.id, s)
        seen.add(item.category)
    assert {"top", "bottom", "suit"} <= seen
    tops = demo_chart("top", "male")[1]
    assert S.nearest_size(tops, {"chest_cm": 101.6, "waist_cm": 92.0}) == "M"
    assert S.nearest_size(tops, {"chest_cm": 113.0}) == "XL"
    assert demo_chart("bottom", "female")[1]["M"] != demo_chart("bottom", "male")[1]["M"]  # the derived hips


def test_bound_size_fits(model, graded) -> None:
    """A bound garment's per-size example fits: on the body a size was graded on, that size's
    rest shape; the base size's fits are the binding's own."""
    g0, faces, rests, on, bodies, chart = graded["pencil-skirt"]
    item = next(i for i in load_catalogue().garments() if i.id == "pencil-skirt")
    fits = S.bound_size_fits(item.binding.fit, on, rests, on)
    assert len(fits) == len(rests)
    for s in range(len(rests)):
        assert np.allclose(fits[s][s], rests[s], atol=1e-5)
    assert np.allclose(fits[chart.base], np.stack([item.binding.fit(X) for X in on]), atol=1e-6)
    assert not np.allclose(fits[0][1], fits[2][1], atol=1e-3)  # sizes differ on the same body
