"""Sizes and fit, the maths (``service.model.sizing``): chart validation, grading keeps the base
size and grows the others, garment girths per region, verdict thresholds per fabric, the
recommendation rule and monotonicity of ease and strain with size; the length regions (sleeve,
inseam, hem: ``service.model.garments.lengths``), their verdicts and stored records without
them."""
from __future__ import annotations

import numpy as np
import pytest

from service.application.sizes import Chart, chart_bodies
from service.model.body.shape import avatar_from_measurements
from service.model.garments import sizing as S
from service.model.garments.catalogue import load_catalogue

GIRTH = np.isin(S.REGIONS, S.GIRTH_REGIONS)

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
    # intervals, as retailers' charts print them: made for the middle, the interval kept
    sizes, _ = S.validate_chart({"S": {"chest_cm": [86, 90], "hip_cm": 94}, "M": {"chest_cm": [90, 98], "hip_cm": 102}},
                                None)
    assert sizes[0] == {"label": "S", "measurements": {"chest_cm": 88.0, "hip_cm": 94.0},
                        "intervals": {"chest_cm": [86.0, 90.0]}}
    assert sizes[1]["measurements"]["chest_cm"] == 94.0
    for value, text in (([90, 86], "low must not be above"), ([90], "interval"), ([86, 90, 94], "interval"),
                        ([86, "90"], "number"), ([86, float("inf")], "finite")):
        with pytest.raises(S.ChartError, match=text):
            S.validate_chart({"S": {"chest_cm": value}}, None)
    with pytest.raises(S.ChartError, match="range"):
        S.validate_chart({"S": {"chest_cm": [58, 62]}}, None, {"chest_cm": (60.0, 160.0)})
    with pytest.raises(S.ChartError, match="increase"):  # the middles must increase
        S.validate_chart({"S": {"chest_cm": [84, 96]}, "M": {"chest_cm": [88, 92]}}, None)
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
        present = np.isfinite(fit.design_cm) & GIRTH
        assert present.any(), name
        for s in range(3):
            own = S.girths_of_body(model, bodies[s])
            ease = fit.garment_cm[s] - own
            assert np.all(np.abs(ease - fit.design_cm)[present] < 1.5), (name, s, ease, fit.design_cm)
        steps = np.diff(fit.garment_cm, axis=0)
        assert np.all(steps[:, present] > 0.5), (name, steps)
        charted = present & np.isin(S.REGIONS, ["chest", "waist", "hip"])
        assert np.all(steps[:, charted] > 5.0), (name, steps)


def test_recommendation_and_monotonicity(model, graded) -> None:
    """Bodies made from each size's chart measurements get that size; on any body ease grows
    and strain falls with the size at every region."""
    for name, (g0, faces, rests, on, bodies, chart) in graded.items():
        fit = S.sized_garment_fit(model, rests, faces, on, chart.labels, chart.base, bodies[chart.base], "knit")
        for s in range(3):
            rep = S.fit_report(fit, S.girths_of_body(model, bodies[s]))
            assert rep.recommended == s, (name, s, rep.to_dict())
            girths = rep.present & GIRTH
            E, T = rep.ease_cm[:, girths], rep.strain_pct[:, girths]
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


def test_a_tape_reads_a_wrinkled_loop_by_its_hull() -> None:
    """A tube whose wall is wrinkled (the radius 15 cm +- 1 cm, 16 waves around): the cloth's
    length along the section counts every wrinkle (~28 % more than the smooth tube), a tape laid
    around it reads the hull: the polygon through the crests, within 1 % of a circle of 16 cm."""
    from tests.drape_cases import tube

    V, F = tube(0.15, 0.2, n_around=64, n_height=4)
    angle = np.arctan2(V[:, 2], V[:, 0])
    r = 0.15 + 0.01 * np.cos(16 * angle)
    V = np.column_stack([r * np.cos(angle), V[:, 1], r * np.sin(angle)])
    region = S.Region(np.array([0.0, 1.0, 0.0]), 0.125, np.array([0.0, 0.125, 0.0]))
    sections = S.GarmentSections(F, len(V))
    cloth, tape = sections.girth(V, region), sections.girth(V, region, tape=True)
    assert cloth > 1.2 * 2 * np.pi * 0.15
    assert tape == pytest.approx(2 * np.pi * 0.16, rel=0.01)
    assert tape < cloth
    # a smooth tube reads the same either way, up to the polygon's corners
    V0, _ = tube(0.15, 0.2, n_around=64, n_height=4)
    assert sections.girth(V0, region, tape=True) == pytest.approx(sections.girth(V0, region), rel=1e-9)
    G = S.garment_girths(sections, V, {n: region for n in S.GIRTH_REGIONS}, tape=True)
    assert np.allclose(G, 100 * tape)


def test_a_closed_girth_is_a_loop_not_a_chain_leaving_the_cloth() -> None:
    """A tube's section is its girth either way. Slit open (a C, 2 cm apart: a chain that leaves
    the cloth, as a section through an armpit running into a sleeve's cuff) it still counts by
    default (the overlapping fronts of a buttoned shirt) but not when ``closed``; cut along a
    seam whose two sides are separate vertices at the same place, it is a loop both ways."""
    from tests.drape_cases import tube

    V, F = tube(0.15, 0.2, n_around=64, n_height=4)
    region = S.Region(np.array([0.0, 1.0, 0.0]), 0.125, np.array([0.0, 0.125, 0.0]))  # between two rings
    full = S.GarmentSections(F, len(V)).girth(V, region)
    assert full == pytest.approx(2 * np.pi * 0.15, rel=0.01)
    assert S.GarmentSections(F, len(V)).girth(V, region, closed=True) == full
    # the seam: the faces between the last and the first column use copies of the first column
    seam = np.arange(5) * 64
    Vs = np.vstack([V, V[seam]])
    copy = {int(v): len(V) + k for k, v in enumerate(seam)}
    last = (F % 64 == 63).any(axis=1) & (F % 64 == 0).any(axis=1)  # the faces from the last column to the first
    Fs = F.copy()
    Fs[last] = np.vectorize(lambda v: copy.get(int(v), int(v)))(F[last])
    for closed in (False, True):
        assert S.GarmentSections(Fs, len(Vs)).girth(Vs, region, closed) == pytest.approx(full, rel=1e-6)
    # the C: drop the last column of faces (the opening is 2 pi 0.15 / 64 = 1.5 cm wide)
    Fc = F[~last]
    open_chain = S.GarmentSections(Fc, len(V)).girth(V, region)
    assert open_chain == pytest.approx(full * 63 / 64, rel=0.01)
    assert S.GarmentSections(Fc, len(V)).girth(V, region, closed=True) is None


def test_a_girth_must_not_enclose_an_excluded_point(model) -> None:
    """A section around the region's centre that also goes around an excluded point is no
    girth: a tube of 15 cm radius reads its girth with a point outside it excluded, none with
    one of two points inside it. On a body the chest excludes both upper arms where their axes
    cross its plane, left and right of the chest's centre (a long sleeve cut where it meets the
    body, the tape around the arms, is not a chest girth)."""
    from tests.drape_cases import tube

    V, F = tube(0.15, 0.2, n_around=64, n_height=4)
    sections = S.GarmentSections(F, len(V))
    plane = (np.array([0.0, 1.0, 0.0]), 0.125, np.array([0.0, 0.125, 0.0]))
    outside, inside = np.array([0.3, 0.125, 0.0]), np.array([0.1, 0.125, 0.0])
    full = sections.girth(V, S.Region(*plane))
    assert full == pytest.approx(2 * np.pi * 0.15, rel=0.01)
    assert sections.girth(V, S.Region(*plane, exclude=outside)) == full
    assert sections.girth(V, S.Region(*plane, exclude=np.stack([outside, inside]))) is None
    chest = S.region_spec(model).regions(model.mean)["chest"]
    assert chest.exclude.shape == (2, 3)
    assert np.allclose(chest.exclude @ chest.normal, chest.offset)
    side = (chest.exclude - chest.centre)[:, 0]
    assert side[0] * side[1] < 0 and (np.abs(side) > 0.12).all()


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


# -- lengths ---------------------------------------------------------------------------------
def _one_size(model, gid: str, body=None) -> S.SizeFit:
    """A catalogue garment's one-size fit on ``body`` (default the mean avatar)."""
    X = np.asarray(model.mean if body is None else body, np.float64)
    item = next(i for i in load_catalogue().garments() if i.id == gid)
    g = np.asarray(item.binding.fit(X))
    return S.sized_garment_fit(model, g[None], np.asarray(item.faces), X, ["one size"], 0, X, "knit")


def _lengths(fit: S.SizeFit) -> set[str]:
    return {r for r, d in zip(S.REGIONS, fit.design_cm) if np.isfinite(d) and r in S.LENGTH_REGIONS}


def test_the_pages_fit_map_legends_match_the_colours() -> None:
    """The page's legend for each fit map (``web_client/app.js``: a CSS gradient of three stops)
    runs through the same hues as the GLB's colours: each stop's dominant channel is that of
    ``strain_colors`` / ``ease_colors`` at the scale's start, middle and end."""
    import re
    from pathlib import Path

    js = (Path(__file__).resolve().parents[1] / "web_client" / "app.js").read_text()
    lim = S.FIT_THRESHOLDS["knit"].strain_limit_pct / 100
    mid = S.fit_gap_m("knit")
    expected = {"strain": S.strain_colors(np.array([0.0, lim / 2, lim]), "knit"),
                "ease": S.ease_colors(np.array([0.0, mid, S.EASE_MAP_HANG_M]), "knit")}
    for kind, colours in expected.items():
        stops = re.search(kind + r": \{ css: 'linear-gradient\(to right, (#\w{6}), (#\w{6}), (#\w{6})\)'", js).groups()
        legend = [[int(h[i:i + 2], 16) for i in (1, 3, 5)] for h in stops]
        assert [int(np.argmax(c)) for c in legend] == [int(np.argmax(c[:3])) for c in colours], (kind, stops)


def test_length_regions_of_catalogue_garments(model) -> None:
    """Long sleeves get a sleeve, T-shirt sleeves do not; trousers an inseam and no hem; tops
    and skirts a hem; the lengths sit where the garments end (a long sleeve near the wrist,
    jeans above the floor, a T-shirt's hem above the crotch, a skirt's below it)."""
    got = {gid: _one_size(model, gid) for gid in ("longsleeve-tee", "mens-tshirt", "womens-tshirt", "mens-jeans",
                                                    "pencil-skirt")}
    assert _lengths(got["longsleeve-tee"]) == {"sleeve", "hem"}
    assert _lengths(got["mens-tshirt"]) == {"hem"} and _lengths(got["womens-tshirt"]) == {"hem"}
    assert _lengths(got["mens-jeans"]) == {"inseam"}
    assert _lengths(got["pencil-skirt"]) == {"hem"}
    ease = lambda gid, r: float(got[gid].design_cm[S.REGIONS.index(r)])  # noqa: E731
    assert -6.0 < ease("longsleeve-tee", "sleeve") < 8.0
    assert -15.0 < ease("mens-jeans", "inseam") < 0.0
    assert ease("mens-tshirt", "hem") < 0.0 < ease("pencil-skirt", "hem")
    # a length's strain is 0, its ease the garment's length minus the body's
    body = S.girths_of_body(model, model.mean)
    rep = S.fit_report(got["longsleeve-tee"], body)
    i = S.REGIONS.index("sleeve")
    assert rep.present[i] and rep.strain_pct[0, i] == 0.0
    assert rep.ease_cm[0, i] == pytest.approx(got["longsleeve-tee"].garment_cm[0, i] - body[i])
    assert any(r["region"] == "sleeve" and r["strain_pct"] == 0.0 for r in rep.to_dict()["sizes"][0]["regions"])


def test_longer_arms_get_a_shorter_sleeve(model) -> None:
    """The same garment on customers differing in arm length only: the longer arm's sleeve ease
    is smaller by about the difference, and 8 cm more arm is a too-short (``too_tight``)
    sleeve; the body's own sleeve length is the measured ``arm_length_cm``."""
    fit = _one_size(model, "longsleeve-tee")
    base = {"gender": "male", "height_cm": 178.0, "chest_cm": 100.0, "waist_cm": 88.0}
    i = S.REGIONS.index("sleeve")
    eases, verdicts = [], []
    for arm in (58.0, 61.0, 66.0):
        body = S.girths_of_body(model, avatar_from_measurements(model, {**base, "arm_length_cm": arm}).vertices)
        assert body[i] == pytest.approx(arm, abs=1.0)
        rep = S.fit_report(fit, body)
        eases.append(float(rep.ease_cm[0, i]))
        verdicts.append(S.VERDICTS[int(rep.verdict[0, i])])
    assert eases[0] > eases[1] > eases[2], eases
    assert eases[0] - eases[2] == pytest.approx(8.0, abs=1.5)
    assert verdicts[2] in ("tight", "too_tight") and verdicts[2] != verdicts[0], (eases, verdicts)


def test_length_verdicts() -> None:
    """Too short is tight, too long loose, on the difference from the design's length ease."""
    regions = ["sleeve", "inseam", "hem"]
    design = np.array([2.0, -3.0, -10.0])
    v = lambda dev: [S.VERDICTS[int(x)] for x in S.length_verdicts(design + np.array(dev), design, regions)]  # noqa: E731
    assert v([0.0, 0.0, 0.0]) == ["fit"] * 3
    assert v([-3.0, -3.0, -3.0]) == ["tight", "tight", "fit"]
    assert v([-6.0, -6.0, -11.0]) == ["too_tight"] * 3
    assert v([5.0, 5.0, 6.0]) == ["loose", "fit", "loose"]
    assert v([9.0, 11.0, 11.0]) == ["too_loose"] * 3


def test_a_too_short_length_counts_as_tight() -> None:
    """Sizes S, M, L whose chest fits M best: M's sleeve too short for this customer -> L
    when the chart sizes lengths (a tailor would not pick a short sleeve); with a chart of
    chest alone (which promises no sleeve length) the short sleeve is reported and the chest
    chooses M; a sleeve short in every size, a short hem or no sleeve: M."""
    R = len(S.REGIONS)
    ci, si = S.REGIONS.index("chest"), S.REGIONS.index("sleeve")
    G = np.full((3, R), np.nan)
    G[:, ci] = [96.0, 104.0, 112.0]
    G[:, si] = [56.0, 58.0, 60.0]
    body_cm = np.full(R, np.nan)
    body_cm[ci], body_cm[si] = 98.0, 62.0
    design = np.where(np.isfinite(G[1]), G[1] - np.array([6.0 if r == "chest" else 0.0 for r in S.REGIONS]), np.nan)
    rep = S.fit_report(S.size_fit(["S", "M", "L"], G, 1, design, "woven", ["chest_cm"]), body_cm)
    assert S.VERDICTS[int(rep.verdict[1, si])] in ("tight", "too_tight")
    assert rep.labels[rep.recommended] == "M"
    fit = S.size_fit(["S", "M", "L"], G, 1, design, "woven", ["chest_cm", "height_cm"])
    rep = S.fit_report(fit, body_cm)
    assert S.VERDICTS[int(rep.verdict[1, si])] in ("tight", "too_tight")
    assert rep.labels[rep.recommended] == "L"
    # short in every size: no size mends it; reported, but the chest chooses
    rep = S.fit_report(fit, np.where(np.arange(R) == si, 70.0, body_cm))
    assert (rep.verdict[:, si] == 0).all() and rep.labels[rep.recommended] == "M"
    # a hem too short in M only does not choose (a style, see CHOOSING_LENGTHS)
    hi = S.REGIONS.index("hem")
    G[:, si] = np.nan
    G[:, hi] = [30.0, 10.0, 30.0]
    body_cm[hi] = 20.0
    fit = S.size_fit(["S", "M", "L"], G, 1, np.where(np.isfinite(G[1]), G[1] - np.array(
        [6.0 if r == "chest" else 0.0 for r in S.REGIONS]), np.nan), "woven")
    rep = S.fit_report(fit, np.where(np.arange(R) == hi, 30.0, body_cm))
    assert S.VERDICTS[int(rep.verdict[1, hi])] == "too_tight" and rep.labels[rep.recommended] == "M"
    G[:, hi] = np.nan
    fit = S.size_fit(["S", "M", "L"], G, 1, np.where(np.isfinite(G[1]), G[1] - 6.0, np.nan), "woven")
    assert S.fit_report(fit, body_cm).labels[S.fit_report(fit, body_cm).recommended] == "M"


def test_stored_fit_without_lengths_still_reads() -> None:
    """A size fit stored before the lengths (its ``regions`` the girths only) reads back with
    no length regions, and reports; a new one round-trips its lengths."""
    old = {"labels": ["S", "M"], "regions": list(S.GIRTH_REGIONS), "fabric": "knit",
           "garment_cm": [[90.0, 80.0, None, None, 30.0, 100.0], [98.0, 88.0, None, None, 32.0, 108.0]],
           "design_cm": [4.0, 6.0, None, None, 2.0, 5.0], "design_body_cm": [94.0, 82.0, None, None, 30.0, 103.0],
           "key": [True, True, False, False, False, False]}
    fit = S.SizeFit.from_meta(old)
    assert fit.garment_cm.shape == (2, len(S.REGIONS)) and not np.isfinite(fit.design_cm[~GIRTH]).any()
    assert list(fit.key) == [True, True] + [False] * (len(S.REGIONS) - 2)
    body = np.array([95.0, 84.0, 100.0, 60.0, 30.0, 104.0, 60.0, 80.0, 20.0])
    regions = {r["region"] for r in S.fit_report(fit, body).to_dict()["sizes"][0]["regions"]}
    assert regions == {"chest", "waist", "upper_arm", "shoulders"}
    new = fit.to_meta()
    new["garment_cm"] = [row[:6] + [58.0, None, -5.0] for row in new["garment_cm"]]
    new["design_cm"] = new["design_cm"][:6] + [2.0, None, -8.0]
    back = S.SizeFit.from_meta(new)
    assert back.garment_cm[1, S.REGIONS.index("sleeve")] == 58.0 and np.isnan(back.design_cm[S.REGIONS.index("inseam")])


CHART_TALL = {"S": {"height_cm": 168.0, "chest_cm": 92.0, "waist_cm": 80.0, "hip_cm": 94.0},
              "M": {"height_cm": 178.0, "chest_cm": 100.0, "waist_cm": 88.0, "hip_cm": 100.0},
              "L": {"height_cm": 188.0, "chest_cm": 108.0, "waist_cm": 96.0, "hip_cm": 106.0}}


@pytest.mark.slow
def test_lengths_grow_with_a_chart_growing_in_height(model) -> None:
    """Graded to a chart that grows in height: each size's sleeve and inseam are longer, the
    ease on one customer grows with the size, and a customer made from each size's chart gets
    about the design's length ease (its own size fits in length)."""
    chart = Chart(S.validate_chart(CHART_TALL, "M")[0], "M", "knit")
    bodies = chart_bodies(model, chart, "male")
    src = np.asarray(model.mean, np.float64)
    on = S.size_bodies_on(src, bodies, chart.base)
    items = {i.id: i for i in load_catalogue().garments()}
    for gid, region in (("longsleeve-tee", "sleeve"), ("mens-jeans", "inseam")):
        item = items[gid]
        faces = np.asarray(item.faces, np.int64)
        rests = S.grade(model, item.binding.fit(src), faces, src, bodies, chart.base)
        fit = S.sized_garment_fit(model, rests, faces, on, chart.labels, chart.base, bodies[chart.base], "knit",
                                  list(CHART_TALL["M"]))
        i = S.REGIONS.index(region)
        assert np.isfinite(fit.garment_cm[:, i]).all(), (gid, fit.garment_cm)
        assert np.all(np.diff(fit.garment_cm[:, i]) > 2.0), (gid, fit.garment_cm[:, i])
        rep = S.fit_report(fit, S.girths_of_body(model, bodies[chart.base]))
        assert np.all(np.diff(rep.ease_cm[:, i]) > 2.0), (gid, rep.ease_cm[:, i])
        for s in range(3):
            own = S.fit_report(fit, S.girths_of_body(model, bodies[s]))
            assert abs(own.ease_cm[s, i] - fit.design_cm[i]) < 2.0, (gid, s, own.ease_cm[s, i], fit.design_cm[i])
            assert S.VERDICTS[int(own.verdict[s, i])] == "fit"


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


def _cylinder(radius: float, n: int = 48, rings: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """A closed-sided cylinder (rings * n, 3) along y, 0.8 m tall, and its faces."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    y = np.linspace(-0.4, 0.4, rings)
    V = np.stack([np.tile(radius * np.cos(a), rings), np.repeat(y, n), np.tile(radius * np.sin(a), rings)], 1)
    F = []
    for r in range(rings - 1):
        for i in range(n):
            p, q = r * n + i, r * n + (i + 1) % n
            F += [[p, p + n, q], [q, p + n, q + n]]
    return V, np.asarray(F, np.int64)


def test_grading_keeps_the_gap_to_the_body() -> None:
    """A tube 2 cm off a cylinder of radius 15 cm, carried to a cylinder of 20 cm by scaling
    (what a warp does: the gap grows to 2.7 cm): ``keep_offsets`` sets it back to 2 cm, so the
    size's ease (2 pi gap) is the base's; a tube 15 cm off (hanging) keeps the warp's."""
    body, F = _cylinder(0.15)
    big = body * [0.20 / 0.15, 1.0, 0.20 / 0.15]
    tube, tF = _cylinder(0.17, rings=5)
    tube[:, 1] *= 0.5
    warped = tube * [0.20 / 0.15, 1.0, 0.20 / 0.15]
    out = S.keep_offsets(tube, warped, body, big, F, tF)
    r = np.hypot(out[:, 0], out[:, 2])
    assert np.abs(r - 0.22).max() < 0.002, (r.min(), r.max())  # the 2 cm gap kept (polygon: ~1 mm)
    far = _cylinder(0.30, rings=5)[0]
    far[:, 1] *= 0.5
    far_warped = far * [0.20 / 0.15, 1.0, 0.20 / 0.15]
    assert np.allclose(S.keep_offsets(far, far_warped, body, big, F), far_warped)


def test_an_open_section_counts_the_body_it_leaves_bare_at_no_ease() -> None:
    """A tube with a sixteenth of it cut away along its length (an open back, an open jacket's
    front: the section leaves 22.5 degrees of the body bare) reads its cloth length alone without
    the body's girth; with it, the cloth plus a sixteenth of the body's girth (the bare arc at no
    ease), whichever side the opening faces (the even-odd rule, which a loop's section is read
    by, found no girth with the opening on its ray). A closed tube reads the same either way."""
    from tests.drape_cases import tube

    V, F = tube(0.15, 0.2, n_around=64, n_height=4)
    region = S.Region(np.array([0.0, 1.0, 0.0]), 0.125, np.array([0.0, 0.125, 0.0]))
    body = 2 * np.pi * 0.14
    full = S.GarmentSections(F, len(V)).girth(V, region)
    assert S.GarmentSections(F, len(V)).girth(V, region, body_girth=body) == full
    col = F % 64
    column = np.where((col == 63).any(axis=1) & (col == 0).any(axis=1), 63, col.min(axis=1))  # each quad's column
    for start in (0, 12, 28, 44, 62):
        Fo = F[~np.isin(column, np.arange(start, start + 4) % 64)]
        sections = S.GarmentSections(Fo, len(V))
        cloth = sections.girth(V, region)
        assert cloth == pytest.approx(full * 60 / 64, rel=1e-6), start
        assert sections.girth(V, region, body_girth=body) == pytest.approx(cloth + body / 16, rel=1e-6), start
    # a garment's girths on a body's regions add the share of that body's girth
    regions = {r: S.Region(region.normal, region.offset, region.centre, body_girth=body) for r in S.GIRTH_REGIONS}
    G = S.garment_girths(sections, V, regions)
    assert G == pytest.approx(np.full(len(S.GIRTH_REGIONS), 100 * (cloth + body / 16)), rel=1e-6)


def test_a_charted_region_the_garment_lacks_is_ranked_by_the_chart() -> None:
    """Sizes S, M, L of a waist chart on a garment with no section at the waist (low-rise
    trousers; dungarees' bib on a chest chart): the chart's own waists rank the sizes there, so
    a customer whose waist is L's gets L, whatever the hips' ease says (which would pick S for a
    narrow-hipped one); without the chart's values (a record of no chart) the regions the
    garment has rank them as before; a size tight somewhere still cannot be picked."""
    R = len(S.REGIONS)
    wi, hi = S.REGIONS.index("waist"), S.REGIONS.index("hip")
    G = np.full((3, R), np.nan)
    G[:, hi] = [96.0, 102.0, 108.0]
    design = np.full(R, np.nan)
    design[hi] = 6.0
    body_cm = np.full(R, np.nan)
    body_cm[wi], body_cm[hi] = 85.0, 90.0  # L's waist, S's hips
    fit = S.size_fit(["S", "M", "L"], G, 1, G[1] - design, "stretch", ["waist_cm"])
    assert S.fit_report(fit, body_cm).recommended == 0
    fit.chart_cm = S.chart_girths([{"waist_cm": 73.0}, {"waist_cm": 79.0}, {"waist_cm": 85.0}])
    assert np.isfinite(fit.chart_cm[:, wi]).all() and np.isnan(np.delete(fit.chart_cm, wi, axis=1)).all()
    assert S.fit_report(fit, body_cm).recommended == 2
    assert S.fit_report(fit, np.where(np.arange(R) == wi, 78.0, body_cm)).recommended == 1
    # a chart of the hip too, where the garment has a section: both count
    fit.key = np.isin(S.REGIONS, ["waist", "hip"])
    assert S.fit_report(fit, np.where(np.arange(R) == wi, 79.0, body_cm)).recommended in (0, 1)
    # L tight at the hips (a woven garment 6 cm under the body there): M
    fit = S.size_fit(["S", "M", "L"], np.where(np.arange(R) == hi, [[96.0], [102.0], [84.0]], G), 1, G[1] - design,
                     "woven", ["waist_cm"])
    fit.chart_cm = S.chart_girths([{"waist_cm": 73.0}, {"waist_cm": 79.0}, {"waist_cm": 85.0}])
    assert S.fit_report(fit, body_cm).recommended == 1


def test_overlapping_fronts_go_around_whichever_way_they_face() -> None:
    """A wrap of cloth that goes 1.1 times around (a buttoned shirt's overlapping fronts, a
    spiral widening by 5 % so the fronts lie one over the other) reads its whole cloth length
    as its girth, with no bare share, whichever way the overlap faces: the even-odd rule's ray
    through the overlap crosses the cloth twice and found no girth there."""
    n, r0 = 72, 0.15
    for start in (0.3, -0.3, 2.0):
        th = start + np.linspace(0.0, 2.2 * np.pi, n)
        rad = r0 * (1.0 + 0.05 * np.linspace(0.0, 1.0, n))
        ring = np.stack([rad * np.cos(th), np.zeros(n), rad * np.sin(th)], 1)
        V = np.concatenate([ring + [0.0, y, 0.0] for y in (0.0, 0.1, 0.2)])
        F = np.array([f for k in range(2) for j in range(n - 1) for f in (
            (k * n + j, (k + 1) * n + j, k * n + j + 1), (k * n + j + 1, (k + 1) * n + j, (k + 1) * n + j + 1))])
        region = S.Region(np.array([0.0, 1.0, 0.0]), 0.05, np.array([0.0, 0.05, 0.0]))
        cloth = float(np.linalg.norm(np.diff(ring, axis=0), axis=1).sum())
        sections = S.GarmentSections(F, len(V))
        assert sections.girth(V, region) == pytest.approx(cloth, rel=1e-6), start
        assert sections.girth(V, region, body_girth=2 * np.pi * 0.14) == pytest.approx(cloth, rel=1e-6), start


def test_a_coarse_loop_around_an_off_centre_point_is_a_girth() -> None:
    """A loop of cloth with few vertices around (a trouser hem of 8, the leg standing off its
    centre) goes all around a point inside it: its girth, though its crossing points leave
    sectors around that point empty (read as no loop before, which cut the trousers' inseam
    short where their hem is coarse). Slit open, the same sparse chain is no girth."""
    from tests.drape_cases import tube

    V, F = tube(0.1, 0.2, n_around=8, n_height=2)
    region = S.Region(np.array([0.0, 1.0, 0.0]), 0.05, np.array([0.06, 0.05, 0.0]))
    ring = V[:8] * [1.0, 0.0, 1.0]
    octagon = float(np.linalg.norm(ring - np.roll(ring, 1, axis=0), axis=1).sum())
    assert S.GarmentSections(F, len(V)).girth(V, region) == pytest.approx(octagon, rel=1e-9)
    col = F % 8
    slit = (col == 7).any(axis=1) & (col == 0).any(axis=1)
    assert S.GarmentSections(F[~slit], len(V)).girth(V, region) is None


# MakeHuman outfits graded to charts of other kinds than the demo's, the sections that made them
# hard: the business suit's coarse trouser hems (length charts), the sports suit's cropped top and
# low-rise trousers (no section at the waist), a casual suit by waist and inseam, another by hip
OTHER_CHARTS = (
    ("male_elegantsuit01", "male", "woven", {f"L{n}": {"inseam_cm": round(n * 2.54, 1)} for n in (28, 30, 32, 34, 36)}),
    ("male_elegantsuit01", "male", "woven", {str(h): {"height_cm": float(h)} for h in (164, 170, 176, 182, 188)}),
    ("female_sportsuit01", "female", "stretch", {k: {"waist_cm": w} for k, w in zip("SMLX", (73.0, 79.0, 85.0, 91.0))}),
    ("female_sportsuit01", "female", "knit", {k: {"chest_cm": c, "waist_cm": c - 16.0, "hip_cm": c + 8.0}
                                              for k, c in zip(("XS", "S", "M", "L", "XL"), (80, 86, 92, 100, 108))}),
    ("male_casualsuit04", "male", "woven", {f"{w}/{n}": {"waist_cm": round(w * 2.54, 1), "inseam_cm": round(n * 2.54, 1)}
                                            for w, n in ((30, 30), (32, 31), (34, 32), (36, 33))}),
    ("female_casualsuit01", "female", "woven", {str(36 + 2 * i): {"hip_cm": 88.0 + 5 * i} for i in range(6)}),
)


@pytest.mark.slow
@pytest.mark.parametrize("name,gender,fabric,chart_dict", OTHER_CHARTS)
def test_other_garments_and_charts_round_trip(model, name: str, gender: str, fabric: str, chart_dict: dict) -> None:
    """A customer made from each size's chart measurements gets that size, on MakeHuman outfits
    graded as an upload is (from the mean avatar, the fit with the chart's measurements as the
    service reads them from the record): charts of lengths alone, a waist chart on a garment with
    no section at the waist, a bust/waist/hip chart, waist and inseam, hip alone."""
    from tests.bench.common import shared_data_dir
    from tests.draped_data import binding

    if not (shared_data_dir() / "makehuman_clothes" / name).is_dir():
        pytest.skip(f"MakeHuman garment {name} not found")
    b, faces = binding(model, name)
    faces = np.asarray(faces, np.int64)
    src = np.asarray(model.mean, np.float64)
    labels = list(chart_dict)
    sizes, base = S.validate_chart(chart_dict, labels[len(labels) // 2])
    chart = Chart(sizes, base, fabric)
    bodies = chart_bodies(model, chart, gender)
    rests = S.grade(model, b.fit(src), faces, src, bodies, chart.base)
    fit = S.sized_garment_fit(model, rests, faces, S.size_bodies_on(src, bodies, chart.base), chart.labels,
                              chart.base, bodies[chart.base], fabric, list(chart_dict[labels[0]]))
    fit.chart_cm = S.chart_girths([chart_dict[lb] for lb in labels])
    got = [labels[S.fit_report(fit, S.girths_of_body(model, avatar_from_measurements(
        model, {"gender": gender, **chart_dict[lb]}).vertices)).recommended] for lb in labels]
    assert got == labels
