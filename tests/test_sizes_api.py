"""Sizes and fit over the API in process: a MakeHuman garment uploaded with a size chart
(graded by the service), the fit report of customers made from each size's chart measurements,
the try-on per size (``?size=``, outfits ``?sizes=``), 422s for bad charts and unknown sizes,
graded meshes uploaded by the retailer (``garment_sizes``) built by the job, and the length
regions (sleeve, inseam, hem) of demo garments."""
from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.bench.common import shared_data_dir
from tests.harness import GLB, RETAILERS, assert_422, redis_db, redis_url

# each test builds garments through the API (seconds each): the full tier
pytestmark = pytest.mark.slow

KEY = {"X-API-Key": RETAILERS["acme"]}
SUIT = shared_data_dir() / "makehuman_clothes" / "male_casualsuit04"
# EN 13402-3 men's chest / waist / hip (cm), sizes 48-52 (the middle of the table)
CHART = {"48": {"chest_cm": 96.0, "waist_cm": 84.0, "hip_cm": 98.0},
         "50": {"chest_cm": 100.0, "waist_cm": 88.0, "hip_cm": 102.0},
         "52": {"chest_cm": 104.0, "waist_cm": 92.0, "hip_cm": 106.0}}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("sizes"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="longsleeve-tee,mens-tshirt,mens-jeans",
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def _suit_files() -> list:
    if not SUIT.is_dir():
        pytest.skip(f"MakeHuman garment not found at {SUIT}")
    return [("mhclo", ("suit.mhclo", (SUIT / "male_casualsuit04.mhclo").read_bytes(), "text/plain")),
            ("obj", ("suit.obj", (SUIT / "male_casualsuit04.obj").read_bytes(), "model/obj"))]


@pytest.fixture(scope="module")
def sized(client: TestClient) -> dict:
    r = client.post("/v1/garments", data={"name": "Suit in sizes", "size_chart": json.dumps(CHART),
                                          "base_size": "50", "fabric": "knit", "gender": "male"},
                    files=_suit_files(), headers=KEY)
    assert r.status_code == 201, r.text
    return r.json()


def _customer(client: TestClient, measurements: dict) -> tuple[str, dict]:
    r = client.post("/v1/customers", json={"measurements": {"gender": "male", **measurements}})
    assert r.status_code == 201, r.text
    return r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}


def test_record_shows_the_chart(client: TestClient, sized: dict) -> None:
    assert [s["label"] for s in sized["sizes"]] == ["48", "50", "52"]
    assert sized["sizes"][0]["measurements"] == CHART["48"]
    assert sized["base_size"] == "50" and sized["fabric"] == "knit" and sized["gender"] == "male"
    again = client.get(f"/v1/garments/{sized['id']}").json()
    assert again["sizes"] == sized["sizes"]


def test_chart_of_intervals(client: TestClient) -> None:
    """A chart as retailers print it, each measurement an interval: the sizes are made for the
    middles, the record keeps the intervals, and a customer in the middle of the largest size's
    intervals gets that size."""
    chart = {label: {k: [v - 2.0, v + 2.0] for k, v in ms.items()} for label, ms in CHART.items()}
    r = client.post("/v1/garments", data={"name": "Suit, chart of intervals", "size_chart": json.dumps(chart),
                                          "base_size": "50", "fabric": "knit", "gender": "male"},
                    files=_suit_files(), headers=KEY)
    assert r.status_code == 201, r.text
    rec = r.json()
    assert [s["measurements"] for s in rec["sizes"]] == list(CHART.values())
    assert [s["intervals"] for s in rec["sizes"]] == list(chart.values())
    assert client.get(f"/v1/garments/{rec['id']}").json()["sizes"] == rec["sizes"]
    cid, auth = _customer(client, CHART["52"])
    fit = client.get(f"/v1/customers/{cid}/garments/{rec['id']}/fit", headers=auth)
    assert fit.status_code == 200 and fit.json()["recommended"] == "52", fit.text


def test_chart_made_customers_get_their_size(client: TestClient, sized: dict) -> None:
    """A customer made from size X's chart measurements: X recommended, its ease at chest,
    waist and hip within 1 cm of the design ease... of the base size on its own body, ease
    growing with size, strain falling."""
    base = None
    for label, ms in CHART.items():
        cid, auth = _customer(client, ms)
        r = client.get(f"/v1/customers/{cid}/garments/{sized['id']}/fit", headers=auth)
        assert r.status_code == 200, r.text
        rep = r.json()
        assert rep["recommended"] == label, rep
        assert [s["label"] for s in rep["sizes"]] == list(CHART)
        regions = {x["region"] for x in rep["sizes"][0]["regions"]}
        assert {"chest", "waist", "inseam"} <= regions and "sleeve" not in regions  # T-shirt and jeans
        for i, reg in enumerate(rep["sizes"][0]["regions"]):
            eases = [s["regions"][i]["ease_cm"] for s in rep["sizes"]]
            strains = [s["regions"][i]["strain_pct"] for s in rep["sizes"]]
            assert eases == sorted(eases) and eases[0] < eases[-1], (reg, eases)
            assert strains == sorted(strains, reverse=True), (reg, strains)
        mine = next(s for s in rep["sizes"] if s["label"] == label)
        if label == "50":
            base = mine
    assert base is not None


def test_try_on_per_size(client: TestClient, sized: dict) -> None:
    cid, auth = _customer(client, CHART["48"])
    gid = sized["id"]
    url = f"/v1/customers/{cid}/garments/{gid}.glb"
    small, large, default = (client.get(url, params=p, headers=auth) for p in ({"size": "48"}, {"size": "52"}, {}))
    for r in (small, large, default):
        assert r.status_code == 200 and r.headers["content-type"] == GLB
    assert small.headers["etag"] != large.headers["etag"]
    assert default.headers["etag"] == small.headers["etag"]  # the recommended size
    r = client.get(url, params={"size": "XXL"}, headers=auth)
    assert_422(r, ["query", "size"])
    assert "48, 50, 52" in r.text
    out = client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": gid, "sizes": "52"}, headers=auth)
    assert out.status_code == 200, out.text
    assert_422(client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": gid, "sizes": "52,48"},
                          headers=auth), ["query", "sizes"])
    assert_422(client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": gid, "sizes": "9"},
                          headers=auth), ["query", "sizes"])


@pytest.mark.parametrize("fields,loc,text", [
    ({"size_chart": "[1, 2]"}, ["body", "size_chart"], "JSON object"),
    ({"size_chart": "{"}, ["body", "size_chart"], "not valid JSON"),
    ({"size_chart": json.dumps({"S": {"chest": 90}})}, ["body", "size_chart"], "unknown measurement"),
    ({"size_chart": json.dumps({"S": {"chest_cm": "90"}})}, ["body", "size_chart"], "number"),
    ({"size_chart": '{"S": {"chest_cm": 90}, "S": {"chest_cm": 94}}'}, ["body", "size_chart"], "repeated"),
    ({"size_chart": json.dumps({"S": {"chest_cm": 90}, "s": {"chest_cm": 94}})}, ["body", "size_chart"], "repeated"),
    ({"size_chart": json.dumps({"S": {"chest_cm": 94}, "M": {"chest_cm": 90}})}, ["body", "size_chart"], "increase"),
    ({"size_chart": json.dumps({"S": {"chest_cm": 90}, "M": {"chest_cm": 94, "hip_cm": 99}})},
     ["body", "size_chart"], "same measurements"),
    ({"size_chart": json.dumps({"S": {"chest_cm": 9}})}, ["body", "size_chart"], "range"),
    ({"size_chart": json.dumps({"S": {"chest_cm": [94, 90]}})}, ["body", "size_chart"], "low must not be above"),
    ({"size_chart": json.dumps({"S": {"chest_cm": [90]}})}, ["body", "size_chart"], "interval"),
    ({"size_chart": json.dumps({"S": {"chest_cm": [88, 300]}})}, ["body", "size_chart"], "range"),
    ({"size_chart": json.dumps({"S": {"chest_cm": 90}}), "base_size": "M"}, ["body", "base_size"], "not a size"),
    ({"base_size": "M"}, ["body", "base_size"], "size_chart"),
    ({"fabric": "silk"}, ["body", "fabric"], "woven, knit, stretch"),
    ({"gender": "women"}, ["body", "gender"], "female|male|unisex"),
])
def test_bad_charts_are_422_before_any_work(client: TestClient, fields: dict, loc: list, text: str) -> None:
    before = len(client.get("/v1/garments").json())
    r = client.post("/v1/garments", data={"name": "x", **fields}, files=_suit_files(), headers=KEY)
    assert_422(r, loc)
    assert text in r.text, r.text
    assert len(client.get("/v1/garments").json()) == before


def test_garment_sizes_count_and_labels(client: TestClient) -> None:
    obj = (SUIT / "male_casualsuit04.obj").read_bytes()
    chart = json.dumps({"S": {"chest_cm": 92}, "M": {"chest_cm": 100}})
    files = [("garment", ("s.obj", obj, "model/obj")), ("garment", ("m.obj", obj, "model/obj"))]
    cases = [({"garment_sizes": "S"}, "2 files"), ({"garment_sizes": "S,L"}, "each size"),
             ({}, "garment_sizes")]
    for extra, text in cases:
        data = {"name": "x", "size_chart": chart, **extra}
        r = client.post("/v1/garments", data=data, files=files, headers=KEY)
        assert r.status_code == 422 and text in r.text, r.text
    r = client.post("/v1/garments", data={"name": "x", "garment_sizes": "S,M"}, files=files, headers=KEY)
    assert r.status_code == 422 and "size_chart" in r.text


def test_one_size_garment_has_a_fit(client: TestClient) -> None:
    r = client.post("/v1/garments", data={"name": "One size", "fabric": "stretch"}, files=_suit_files(), headers=KEY)
    assert r.status_code == 201, r.text
    g = r.json()
    assert g["sizes"] == [{"label": "one size", "measurements": {}, "intervals": None}] and g["fabric"] == "stretch"
    cid, auth = _customer(client, {"height_cm": 180})
    rep = client.get(f"/v1/customers/{cid}/garments/{g['id']}/fit", headers=auth).json()
    assert rep["recommended"] == "one size" and len(rep["sizes"]) == 1
    assert client.get(f"/v1/customers/{cid}/garments/{g['id']}.glb", params={"size": "one size"},
                      headers=auth).status_code == 200
    assert_422(client.get(f"/v1/customers/{cid}/garments/{g['id']}.glb", params={"size": "M"}, headers=auth),
               ["query", "size"])


def _build(client: TestClient, r) -> dict:
    """The build job of a 202 upload run here (the queue's job, called in process)."""
    assert r.status_code == 202, r.text
    g = r.json()
    assert g["status"] == "building"
    garments = client.app.state.context.garments
    # TRYON_GARMENT_TIMEOUT per size: the graded garment drapes each size on every body
    assert garments.queue.fetch(g["job"]["id"]).timeout == garments.settings.garment_timeout * len(g["sizes"]) > 0
    out = garments.run_build(g["id"], lambda f, m: None)
    assert out["status"] == "done", out
    g = client.get(f"/v1/garments/{g['id']}").json()
    assert g["status"] == "ready"
    return g


def _on_mean_obj(client: TestClient, scale: float = 1.0) -> tuple[bytes, np.ndarray]:
    from service.application.scenes import obj_text
    from tests.draped_data import binding

    model = client.app.state.body_model
    b, faces = binding(model, "male_casualsuit04")
    G = b.fit(model.mean) * scale
    return obj_text(G, faces).encode(), G


def test_one_garment_graded_by_the_job(client: TestClient) -> None:
    """Upload to ready: one draped ``garment`` with a chart, graded by the build job; the base
    size keeps the uploaded mesh; a chart-made customer of the small size gets it."""
    obj, _ = _on_mean_obj(client)
    chart = {k: CHART[k] for k in ("48", "52")}
    r = client.post("/v1/garments", data={"name": "Draped in sizes", "size_chart": json.dumps(chart),
                                          "base_size": "52"},
                    files=[("garment", ("suit.obj", obj, "model/obj"))], headers=KEY)
    g = _build(client, r)
    assert [s["label"] for s in g["sizes"]] == ["48", "52"] and g["base_size"] == "52"
    cid, auth = _customer(client, CHART["48"])
    rep = client.get(f"/v1/customers/{cid}/garments/{g['id']}/fit", headers=auth).json()
    assert rep["recommended"] == "48", rep
    assert client.get(f"/v1/customers/{cid}/garments/{g['id']}.glb", headers=auth).status_code == 200


def test_graded_meshes_uploaded(client: TestClient) -> None:
    """Upload to ready: the retailer's graded meshes (``garment_sizes``, files in any order),
    draped on one body; the larger mesh is the larger size: its ease is larger at every girth."""
    small, _ = _on_mean_obj(client, 0.97)
    large, _ = _on_mean_obj(client, 1.03)
    chart = {"S": CHART["48"], "L": CHART["52"]}
    r = client.post("/v1/garments", data={"name": "Graded", "size_chart": json.dumps(chart), "base_size": "S",
                                          "garment_sizes": "L,S", "fabric": "stretch", "gender": "unisex"},
                    files=[("garment", ("l.obj", large, "model/obj")), ("garment", ("s.obj", small, "model/obj"))],
                    headers=KEY)
    g = _build(client, r)
    assert [s["label"] for s in g["sizes"]] == ["S", "L"] and g["fabric"] == "stretch" and g["gender"] == "unisex"
    cid, auth = _customer(client, CHART["50"])
    rep = client.get(f"/v1/customers/{cid}/garments/{g['id']}/fit", headers=auth).json()
    s, lg = rep["sizes"]
    # girths (the meshes are scaled about the floor: the larger one's legs end higher, its inseam
    # is shorter)
    for a, b in zip(s["regions"], lg["regions"]):
        if a["region"] not in ("sleeve", "inseam", "hem"):
            assert b["ease_cm"] > a["ease_cm"] + 1.0, (a, b)
    # a mesh that is not the same garment: 422 before any job
    bad = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    r = client.post("/v1/garments", data={"name": "Graded", "size_chart": json.dumps(chart), "garment_sizes": "S,L"},
                    files=[("garment", ("s.obj", small, "model/obj")), ("garment", ("l.obj", bad, "model/obj"))],
                    headers=KEY)
    assert r.status_code == 422, r.text


def test_fit_map(client: TestClient, sized: dict, validate_glb) -> None:
    """``?fitmap=strain|ease`` on a try-on and an outfit: COLOR_0 on a white material,
    validator-clean; the small size is more strained on a large customer than the large size."""
    from tests.conftest import valid_glb

    cid, auth = _customer(client, CHART["52"])
    gid = sized["id"]
    url = f"/v1/customers/{cid}/garments/{gid}.glb"
    red = {}
    for size in ("48", "52"):
        r = client.get(url, params={"size": size, "fitmap": "strain"}, headers=auth)
        assert r.status_code == 200, r.text
        glb = valid_glb(validate_glb, r.content)
        assert glb["colors"] is not None and glb["colors"].shape == (len(glb["positions"]), 4)
        red[size] = float(glb["colors"][:, 0].mean())
    # (the map's stretch is each vertex's mean edge stretch: on this suit the small size is ~1.6x as red)
    assert red["48"] > red["52"] + 0.02 and red["48"] > 1.4 * red["52"], red
    plain = client.get(url, params={"size": "52"}, headers=auth)
    assert valid_glb(validate_glb, plain.content)["colors"] is None
    for params in ({"fitmap": "ease"}, {"fitmap": "ease", "compression": "quantize"},
                   {"fitmap": "strain", "compression": "meshopt"}):
        r = client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": gid, **params}, headers=auth)
        assert r.status_code == 200, r.text
        glb = valid_glb(validate_glb, r.content)
        cols = [m["colors"] for m in glb["meshes"] if m["colors"] is not None]
        assert len(cols) == 1
        if params["fitmap"] == "ease":
            c = cols[0]
            assert (c[:, 0] > 0.9).any() and (c[:, 1] > 0.5).any(), "contact and designed fit both shown"
    assert_422(client.get(url, params={"fitmap": "heat"}, headers=auth), ["query", "fitmap"])


def test_fit_report_lengths(client: TestClient) -> None:
    """The demo long-sleeve tee has a ``sleeve`` (and a ``hem``), the T-shirt no sleeve, the
    jeans an ``inseam`` and no hem; a length's strain is 0; a customer with 8 cm longer arms
    gets 8 cm less sleeve ease and a too-short (tight) sleeve. Responses valid FitResponses."""
    from service.api.schemas import FitResponse

    demo = {g["catalogue_id"]: g["id"] for g in client.get("/v1/garments").json() if g["owner"] == "demo"}
    body = {"height_cm": 178.0, "chest_cm": 100.0, "waist_cm": 88.0}
    cid, auth = _customer(client, {**body, "arm_length_cm": 58.0})
    long_cid, long_auth = _customer(client, {**body, "arm_length_cm": 66.0})

    def regions(name: str, who: str, headers: dict) -> dict:
        r = client.get(f"/v1/customers/{who}/garments/{demo[name]}/fit", headers=headers)
        assert r.status_code == 200, r.text
        FitResponse.model_validate(r.json())
        return {x["region"]: x for x in r.json()["sizes"][0]["regions"]}

    tee = regions("longsleeve-tee", cid, auth)
    assert {"sleeve", "hem", "chest"} <= set(tee) and "inseam" not in tee
    assert tee["sleeve"]["strain_pct"] == 0.0 and tee["hem"]["strain_pct"] == 0.0
    short = regions("mens-tshirt", cid, auth)
    assert "sleeve" not in short and "hem" in short
    jeans = regions("mens-jeans", cid, auth)
    assert "inseam" in jeans and "hem" not in jeans and "sleeve" not in jeans
    longer = regions("longsleeve-tee", long_cid, long_auth)
    assert longer["sleeve"]["ease_cm"] == pytest.approx(tee["sleeve"]["ease_cm"] - 8.0, abs=1.5), (tee, longer)
    assert longer["sleeve"]["verdict"] in ("tight", "too_tight") and tee["sleeve"]["verdict"] != longer["sleeve"]["verdict"]


# -- the demo catalogue in sizes -------------------------------------------------------------
@pytest.fixture(scope="module")
def demo_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """An app whose demo catalogue is the men's T-shirt, in sizes (test apps build one size)."""
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("demo-sizes"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="mens-tshirt", TRYON_DEMO_SIZES=True)
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def test_demo_garment_in_sizes(demo_client: TestClient) -> None:
    """The demo men's T-shirt is built in the five EN 13402-3 sizes of its chart, shipped as
    the size nearest the mean avatar (M); a customer made from the M row gets M; XS and XL
    try-ons differ (each size's basis) and XL's garment girth is the larger; a second start
    keeps it, sizes off rebuilds it in one size, sizes on again in five."""
    from service.model.formats.gltf_read import read_glb
    from service.model.garments.demo_sizes import demo_chart

    client = demo_client
    listed = [g for g in client.get("/v1/garments").json() if g.get("catalogue_id") == "mens-tshirt"]
    assert len(listed) == 1
    g = client.get(f"/v1/garments/{listed[0]['id']}").json()
    chart = demo_chart("top", "male")[1]
    assert [s["label"] for s in g["sizes"]] == ["XS", "S", "M", "L", "XL"]
    assert [s["measurements"] for s in g["sizes"]] == [chart[k] for k in chart]
    assert g["base_size"] == "M" and g["fabric"] == "knit" and g["status"] == "ready"

    cid, auth = _customer(client, chart["M"])
    rep = client.get(f"/v1/customers/{cid}/garments/{g['id']}/fit", headers=auth).json()
    assert rep["recommended"] == "M", rep
    assert [s["label"] for s in rep["sizes"]] == list(chart)
    url = f"/v1/customers/{cid}/garments/{g['id']}.glb"
    xs, xl = (client.get(url, params={"size": s}, headers=auth) for s in ("XS", "XL"))
    assert xs.status_code == 200 and xl.status_code == 200
    assert xs.headers["etag"] != xl.headers["etag"]
    P = [np.asarray(read_glb(r.content)["positions"], np.float64) for r in (xs, xl)]
    assert P[0].shape == P[1].shape and np.abs(P[0] - P[1]).max() > 1e-3  # each size its own basis
    # the garment's own girths (ease on one body): XL wider than XS by about the chart's 32 cm
    chest = {s["label"]: next(r["ease_cm"] for r in s["regions"] if r["region"] == "chest") for s in rep["sizes"]}
    assert chest["XL"] - chest["XS"] > 25.0, chest
    assert list(chest) == sorted(chest, key=chest.__getitem__), chest  # growing with size

    garments = client.app.state.context.garments
    assert garments.ensure_demo() == [g["id"]]  # idempotent: nothing rebuilt
    garments.settings.demo_sizes = False
    try:
        one = garments.ensure_demo()
    finally:
        garments.settings.demo_sizes = True
    assert one != [g["id"]]  # rebuilt in one size, the sized one removed
    assert client.get(f"/v1/garments/{g['id']}").status_code == 404
    assert [s["label"] for s in client.get(f"/v1/garments/{one[0]}").json()["sizes"]] == ["one size"]
    again = garments.ensure_demo()  # the catalogue defines 5 sizes again: rebuilt in sizes
    assert again != one and len(client.get(f"/v1/garments/{again[0]}").json()["sizes"]) == 5


def test_a_chart_region_the_garment_does_not_reach_is_ranked_by_the_chart(client: TestClient) -> None:
    """The MakeHuman sports suit (a cropped top and low-rise trousers: no section of it goes
    around the waist) sized by a waist chart: a woman whose waist is the largest size's and
    whose hips are narrow gets the largest size (the chart's waists rank the sizes where the
    garment has no waist; by its other regions alone she got S)."""
    suit = shared_data_dir() / "makehuman_clothes" / "female_sportsuit01"
    if not suit.is_dir():
        pytest.skip(f"MakeHuman garment not found at {suit}")
    chart = {"S": {"waist_cm": 73.0}, "M": {"waist_cm": 79.0}, "L": {"waist_cm": 85.0}, "XL": {"waist_cm": 91.0}}
    files = [("mhclo", ("s.mhclo", (suit / "female_sportsuit01.mhclo").read_bytes(), "text/plain")),
             ("obj", ("s.obj", (suit / "female_sportsuit01.obj").read_bytes(), "model/obj"))]
    r = client.post("/v1/garments", data={"name": "Sports suit by waist", "size_chart": json.dumps(chart),
                                          "base_size": "M", "fabric": "stretch", "gender": "female"},
                    files=files, headers=KEY)
    g = _build(client, r) if r.status_code == 202 else r.json()
    r = client.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 157, "chest_cm": 89.4,
                                                            "waist_cm": 90.0, "hip_cm": 96.0}})
    assert r.status_code == 201, r.text
    auth = {"Authorization": f"Bearer {r.json()['token']}"}
    rep = client.get(f"/v1/customers/{r.json()['id']}/garments/{g['id']}/fit", headers=auth).json()
    assert "waist" not in {x["region"] for x in rep["sizes"][0]["regions"]}, rep
    assert rep["recommended"] == "XL", rep
