"""End to end: the customer page (web_client/) in Debian's chromium, driven by playwright-core
(node, tests/web_client.spec.mjs) against a real `tryon serve` (embedded back end): the form,
sliders, poses, the catalogue (the shopper's gender first, "Show all"), bodies at their real
height on screen, five bodies (and a 208 cm one) in two outfits seen from the front, side and
back, two dressed bodies on a phone (screenshots under tests/artifacts/web_client/, printed),
the layout at 1280x800 and on a phone (the measurements before the catalogue), the privacy line
and "Delete my data", the exact drape ("Draped on you": outfit.glb?drape=exact), sizes (a picker, the fit in words, the fit map: when the server lists
garments in sizes; hidden for one-size garments), a clothed scan edited live over the WebSocket."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from service.model.formats.mesh_io import read_mesh_file
from service.settings import Settings
from tests.bench import synthetic_scans as S
from tests.bench.common import heldout_people
from tests.harness import REPO, run_server

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)

CHROMIUM = Path("/usr/bin/chromium")
SPEC = REPO / "tests" / "web_client.spec.mjs"
ARTIFACTS = REPO / "tests" / "artifacts" / "web_client"
BONES = ["pelvis", "spine", "chest", "neck", "head", "upper_arm_l", "forearm_l", "hand_l",
         "upper_arm_r", "forearm_r", "hand_r", "thigh_l", "shin_l", "foot_l", "thigh_r", "shin_r", "foot_r"]


def _inside(p: dict, margin: float = 0.0) -> bool:
    """A projected point (CSS px) lies inside its canvas."""
    return margin <= p["x"] <= p["width"] - margin and margin <= p["y"] <= p["height"] - margin


def test_customer_page_end_to_end(tmp_path: Path, model) -> None:
    node = shutil.which("node")
    if node is None or not CHROMIUM.is_file():
        pytest.fail("node and /usr/bin/chromium are needed (apt-get install -y chromium; see .ci/run)")
    if not (REPO / "node_modules" / "playwright-core").is_dir() or not (REPO / "node_modules" / "three").is_dir():
        pytest.fail("run `npm ci` at the repo root (playwright-core, three)")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS.parent / ".gitignore").write_text("*\n")
    # the demo catalogue in sizes: the page's size picker, fit words and fit map are exercised
    with run_server(tmp_path / "data", "embedded", TRYON_DEMO_SIZES="true") as server:
        base = str(server.client.base_url).rstrip("/")
        assert server.client.get("/vendor/three/build/three.module.js").status_code == 200
        # a clothed mesh scan, fitted by the server's job while the browser works on the rest
        p = heldout_people(model, 2)[1]
        scan = S.make_scan(model, np.random.default_rng(5), p["weights"], p["gender"], clothed=True,
                           point_cloud=False, n_points=8000, max_pose_deg=15.0, unit="cm", up="+y")
        r = server.client.post("/v1/customers", files={"mesh": ("scan.ply", S.scan_file_bytes(scan, "ply"))})
        assert r.status_code == 202, r.text
        scan_id, scan_token = r.json()["id"], r.json()["token"]
        proc = subprocess.run([node, str(SPEC), base, str(ARTIFACTS), scan_id, scan_token], cwd=REPO,
                              capture_output=True, text=True, timeout=1800, check=False)  # a loaded 2-core machine: ~15 min
        assert proc.returncode == 0, f"{proc.stdout}\n{proc.stderr}"
        out = json.loads(proc.stdout.strip().splitlines()[-1])
        (ARTIFACTS / "facts.json").write_text(json.dumps(out, indent=1))
        for p in out["screenshots"]:
            print(f"screenshot: {p}")
        deleted = server.client.get(f"/v1/customers/{out['deletedCustomer']}",
                                    headers={"Authorization": f"Bearer {out['deletedToken']}"})

    # the avatar: one skinned mesh with the 17 bones, the canvas not blank
    # the body, eyes, eyebrows, hair and underwear (the avatar's look, issue 11)
    assert out["avatar"]["skinned"] == 5 and out["avatar"]["meshes"] == 5
    assert out["avatar"]["bones"] == BONES
    assert out["avatar"]["values"] == {"gender": "male", "height_cm": 180, "weight_kg": 80}
    assert abs(out["avatar"]["height"] - 1.80) < 0.03
    assert out["canvas"]["max"] - out["canvas"]["min"] > 40 and out["canvas"]["colours"] > 10
    # the hair selector: "Default style" (the server's default for the gender) shows hair, "No
    # hair" shows none (it once sent nothing, i.e. the default style), a chosen style shows hair
    assert out["hair"]["labels"][:2] == ["Default style", "No hair"], out["hair"]
    assert out["hair"]["defaultShown"] and not out["hair"]["none"], out["hair"]
    assert out["hair"]["chosen"] and out["hair"]["back"], out["hair"]
    assert out["heightInches"] == "70.9"  # 180 cm in inches
    # a slider: the form follows, the avatar grows
    assert out["formAfterSlider"] == "195"
    assert out["sliderLabel"].startswith("195"), out["sliderLabel"]
    assert out["heightAfterSlider"] > out["avatar"]["height"] + 0.1
    # a pose preset rotates the bones (and survives reloading the scene with garments)
    assert out["boneBefore"] == [0, 0, 0, 1] and out["boneAfter"] != out["boneBefore"]
    assert out["pose"] == "walking" and out["dressed"]["pose"] == "walking"
    assert out["dressed"]["thigh"] == pytest.approx(out["thighAfter"], abs=1e-9)
    # dressed: avatar + a top + a bottom, one skeleton; the customer was saved on the way
    assert out["dressed"]["meshes"] == 7 and out["dressed"]["skinned"] == 7  # the look + 2 garments
    assert out["dressed"]["worn"] == out["expectedWorn"]
    assert out["dressed"]["bones"] == BONES
    assert out["dressed"]["customer"] and out["storedId"] == out["dressed"]["customer"]
    assert out["dressedCanvas"]["colours"] > 10
    # until the body's adapted poses arrive the page poses with the plain directions, every
    # corrective (made for the adapted poses) at 0
    assert out["poseSourceHeld"] == "directions"
    # (the avatar has pose targets too where skin shows through the clothes: correctives.body_tucks)
    assert len({k: v for k, v in out["correctivesHeld"].items() if k != "avatar"}) == 2, out["correctivesHeld"]
    for influences in out["correctivesHeld"].values():
        assert influences and not any(influences.values()), influences
    # each garment carries one pose-corrective target per preset; the current pose's at 1
    for key, pose in (("correctivesWalking", "walking"), ("correctivesHips", "hands-on-hips")):
        got = out[key]
        assert len({k: v for k, v in got.items() if k != "avatar"}) == 2, (key, got)  # the two garments
        for influences in got.values():
            assert {"pose:a-pose", "pose:walking", "pose:arms-down", "pose:hands-on-hips"} <= set(influences)
            assert influences == {k: float(k == f"pose:{pose}") for k in influences}, (key, influences)
    # the exact drape: on by default; "Draped on you" swaps in the outfit as draped on the body
    # (outfit.glb?drape=exact) after the instant try-on; "Instant" goes back to the basis
    d = out["drape"]
    assert out["drapeDefault"] == "exact" and d["visible"] and d["pressed"] == "true", d
    assert "drape=exact" in d["glb"] and "/outfit.glb?" in d["glb"] and d["loads"] >= 2, d
    assert d["status"] == "Draped on your body." and "draped on that body" in d["privacy"], d
    assert "drape=exact" not in d["after"] and d["hiddenAfter"] == "", d
    # the privacy line tells the truth: nothing before the first save / garment, then what is
    # stored (measurements, shape weights), where the key is (this browser's localStorage) and
    # for how long (the service has no customer expiry: until deleted)
    assert not [f for f in Settings.model_fields if "ttl" in f or "expir" in f or "retention" in f], \
        "customers now expire: say for how long in web_client/app.js privacyText()"
    before, stored = out["privacyBefore"], out["privacyStored"]
    assert "Nothing is stored yet" in before and out["deleteDisabledBefore"]
    for text in (before, stored):
        for words in ("measurements", "shape weights", "random id", "localStorage", "until you delete it"):
            assert words in text, (words, text)
    assert out["dressed"]["customer"] in stored and stored.startswith("Stored")
    # delete my data: gone server-side, forgotten client-side
    assert out["customerStatusBefore"] == 200 and out["storedToken"]  # the page keeps the token with the id
    assert out["customerStatusNoToken"] == 404  # and the customer is private without it
    assert deleted.status_code == 404
    assert out["storedAfterDelete"] is None and out["tokenAfterDelete"] is None
    # after a reload the remembered customer's own measurements are back in the form
    assert out["restored"]["customer"] == out["customerBeforeReload"]
    assert float(out["restored"]["height"]) == pytest.approx(out["restoredExpected"]["height"], abs=0.6)
    assert float(out["restored"]["weight"]) == pytest.approx(out["restoredExpected"]["weight"], abs=0.6)
    # the error path: the API's message inline next to the field
    assert "outside the allowed range" in out["inlineError"]
    assert out["lastError"].startswith("height_cm:")
    # a phone width: no horizontal scrolling, the viewer first, the avatar framed, then the
    # measurements (within the first screen and a half, not ~2,500 px down), then the catalogue
    assert out["phoneMeasurements"]["y"] + out["phoneMeasurements"]["height"] <= out["phoneCatalogue"]["y"] + 1
    assert out["phoneMeasurements"]["y"] < 1.5 * 844, out["phoneMeasurements"]
    assert out["phoneScrollWidth"] <= 390
    assert out["phoneViewer"]["width"] > 350 and out["phoneViewer"]["height"] > 400
    assert _inside(out["phoneHead"], 2)
    # ... and the pose buttons (two rows there) below the avatar, not over its legs
    assert out["phoneCanvas"]["y"] + out["phoneScene"]["y1"] <= out["phonePoses"]["y"] + 2, \
        (out["phoneCanvas"], out["phoneScene"], out["phonePoses"])

    # 1280x800: the viewer and the catalogue side by side, both in the window, no page scroll
    lay = out["layout"]
    assert lay["scrollHeight"] <= lay["innerHeight"]
    v, c, g = lay["viewer"], lay["catalogue"], lay["firstGarment"]
    assert c["x"] >= v["x"] + v["width"] - 1  # to the right of the viewer
    assert lay["measurements"]["y"] + lay["measurements"]["height"] <= c["y"]  # the measurements above it
    assert v["width"] >= 700 and v["height"] >= 600
    for b in (v, g):
        assert b["y"] >= 0 and b["y"] + b["height"] <= lay["innerHeight"] and b["x"] + b["width"] <= 1280

    # five bodies (and 208 cm), two outfits, front/side/back: the whole body in the canvas
    # (the top of the head with a margin), each garment drawn where it is
    assert len(out["bodies"]) == 6
    for body in out["bodies"]:
        assert len(body["views"]) == 6, body["name"]
        for view in body["views"]:
            where = f'{body["name"]} outfit {view["outfit"]} {view["view"]}'
            assert _inside(view["head"], 5), (where, view["head"])
            sb = view["scene"]
            assert sb["y0"] >= 0 and sb["y1"] <= sb["height"], (where, sb)
            if view["view"] == "front":  # as framed (the side and back views are orbited, not reframed)
                assert sb["y1"] <= out["posesTop"] + 2, (where, sb, out["posesTop"])  # no button over the feet
            assert len(view["names"]) >= 3, (where, view["names"])
            for name, px in (view.get("pixels") or {}).items():
                assert px is not None, (where, name, view["names"])
                assert px["changed"] > 0.15 and px["notBackground"] > 0.3, (where, name, px)
    tall = out["bodies"][-1]
    assert tall["height"] > 2.0
    assert np.allclose(tall["directionBefore"], tall["directionAfter"], atol=1e-3)  # orbit kept
    assert _inside(tall["headTurned"], 5)
    # real height on screen: the same pixels per metre for every body (the camera frames the
    # tallest body the model makes, whatever the body), so a 150 cm body is drawn 150/190 of a
    # 190 cm one; and it is not lost in the view either
    h150, h190 = out["heightOnScreen"]
    assert h150["px"] / h190["px"] == pytest.approx(h150["metres"] / h190["metres"], rel=0.03), out["heightOnScreen"]
    assert h190["px"] - h150["px"] > 0.15 * h190["px"]
    assert h190["ruler"] == pytest.approx(1.90, abs=0.03) and h150["ruler"] == pytest.approx(1.50, abs=0.03)
    per_metre = [(b["views"][0]["scene"]["y1"] - b["views"][0]["scene"]["y0"]) / b["views"][0]["metres"]
                 for b in out["bodies"]]
    assert max(per_metre) / min(per_metre) < 1.06, per_metre
    for body in out["bodies"]:
        front = body["views"][0]["scene"]
        assert (front["y1"] - front["y0"]) / front["height"] > 0.5, body["name"]

    # the catalogue: the shopper's gender (and unisex) first, the others behind "Show all"
    cat = out["catalogue"]
    assert set(cat["female"]["genders"]) <= {"female", "unisex", None} and "female" in cat["female"]["genders"]
    assert set(cat["male"]["genders"]) <= {"male", "unisex", None} and "male" in cat["male"]["genders"]
    assert cat["female"]["count"] < cat["female"]["total"] and cat["female"]["buttonShown"]
    assert cat["all"]["count"] == cat["all"]["total"]
    assert cat["femaleAgain"]["genders"] == cat["female"]["genders"]
    assert "women" in cat["female"]["title"] and "men" in cat["male"]["title"]

    # sizes: one-size garments (or a server without sizes) show no size UI and ask for no size
    sz = out["sizes"]
    for w in sz["worn"]:
        if len(w["sizes"]) <= 1:
            assert w["picker"] is None, w
    if not sz["sizedInCatalogue"]:
        assert not sz["sectionShown"] and "sizes=" not in sz["glbBefore"] and "fitmap=" not in sz["glbBefore"]
    else:  # a garment in sizes: the picker in chart order, the recommended size marked and tried on
        s = sz["sized"]
        assert s["fitStatus"] == 200, s
        fit, picker = s["fit"], s["picker"]
        assert picker["labels"] == s["sizes"] == [x["label"] for x in fit["sizes"]]
        assert picker["recommended"] == [fit["recommended"]] and picker["pressed"] == [fit["recommended"]]
        # the recommendation in words: the closest size when every size is tight or short somewhere
        rec_verdict = next(x["verdict"] for x in fit["sizes"] if x["label"] == fit["recommended"])
        want = (f"No size fits you everywhere; {fit['recommended']} comes closest." if rec_verdict in ("tight", "too_tight")
                else f"We recommend {fit['recommended']} for you.")
        assert picker["recommendText"] == want, (picker, rec_verdict)
        # another size chosen: pressed, tried on (?sizes= in the order of ?garments=), its fit in words
        assert s["pickerOther"]["pressed"] == [s["other"]]
        from urllib.parse import parse_qs, urlparse
        q = parse_qs(urlparse(s["glbOther"]).query)
        garments_q, sizes_q = q["garments"][0].split(","), q["sizes"][0].split(",")
        assert sizes_q[garments_q.index(s["id"])] == s["other"], s["glbOther"]
        chosen = next(x for x in fit["sizes"] if x["label"] == s["other"])
        words = s["pickerOther"]["words"]
        assert s["wordsExpected"] in words
        off_fit = [r for r in chosen["regions"] if r["verdict"] != "fit"]
        assert ("Fits well everywhere" in words) == (not off_fit), (words, chosen)
        for r in off_fit:  # girths tight / loose, lengths short / long
            said = {"too_tight": ("too tight", "much too short"), "tight": ("tight", "short"),
                    "loose": ("loose", "long"), "too_loose": ("too loose", "much too long")}[r["verdict"]]
            assert any(w in words.lower() for w in said), (words, r)
        # the fit maps: asked for, drawn in vertex colours, with a legend; off: none
        for mode in ("strain", "ease"):
            fm = s["fitmap"][mode]
            assert f"fitmap={mode}" in fm["glb"] and fm["legend"] and fm["coloured"], fm
        assert not s["fitmap"]["off"]["coloured"] and not s["fitmap"]["off"]["legend"]

    # the scan customer: its scan (not the body) over the WebSocket, reshaped live
    assert out["scanRecord"]["status"] == "ready", out["scanRecord"]
    sc = out["scan"]
    n_read = len(read_mesh_file(S.scan_file_bytes(scan, "ply"), "scan.ply").points)  # as the server reads it
    assert sc["first"]["kind"] == "scan" and sc["first"]["vertices"] == n_read and sc["first"]["catalogueHidden"]
    assert "token" not in sc["first"]["url"]  # dropped from the address bar
    assert _inside(sc["first"]["head"], 5)
    (_, h0, d0), (_, h1, d1) = sc["first"]["size"], sc["heavier"]["size"]
    assert d1 > d0 + 0.01 and abs(h1 - h0) < 0.03  # +20 kg: deeper, as tall
    assert sc["heavier"]["frames"] > sc["first"]["frames"] and not sc["heavier"]["errors"]
    assert sc["posed"]["frames"] > sc["heavier"]["frames"] and not sc["posed"]["errors"]
    assert sc["body"]["view"] == "body"
    assert not [m for m in out["console"] if m.startswith("pageerror")], out["console"]
