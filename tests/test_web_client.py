"""End to end: the customer page (web_client/) in Debian's chromium, driven by playwright-core
(node, tests/web_client.spec.mjs) against a real `tryon serve` (embedded back end)."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.tryon_server import REPO, run_server

CHROMIUM = Path("/usr/bin/chromium")
SPEC = REPO / "tests" / "web_client.spec.mjs"
ARTIFACTS = REPO / "tests" / "artifacts" / "web_client"
BONES = ["pelvis", "spine", "chest", "neck", "head", "upper_arm_l", "forearm_l", "hand_l",
         "upper_arm_r", "forearm_r", "hand_r", "thigh_l", "shin_l", "foot_l", "thigh_r", "shin_r", "foot_r"]


def test_customer_page_end_to_end(tmp_path: Path) -> None:
    node = shutil.which("node")
    if node is None or not CHROMIUM.is_file():
        pytest.fail("node and /usr/bin/chromium are needed (apt-get install -y chromium; see .ci/run)")
    if not (REPO / "node_modules" / "playwright-core").is_dir() or not (REPO / "node_modules" / "three").is_dir():
        pytest.fail("run `npm ci` at the repo root (playwright-core, three)")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS.parent / ".gitignore").write_text("*\n")
    with run_server(tmp_path / "data", "embedded", 0) as server:
        base = str(server.client.base_url).rstrip("/")
        assert server.client.get("/vendor/three/build/three.module.js").status_code == 200
        proc = subprocess.run([node, str(SPEC), base, str(ARTIFACTS)], cwd=REPO, capture_output=True,
                              text=True, timeout=150, check=False)
        assert proc.returncode == 0, f"{proc.stdout}\n{proc.stderr}"
        out = json.loads(proc.stdout.strip().splitlines()[-1])
        for p in out["screenshots"]:
            print(f"screenshot: {p}")
        deleted = server.client.get(f"/v1/customers/{out['deletedCustomer']}")

    # the avatar: one skinned mesh with the 17 bones, the canvas not blank
    assert out["avatar"]["skinned"] == 1 and out["avatar"]["meshes"] == 1
    assert out["avatar"]["bones"] == BONES
    assert out["avatar"]["values"] == {"gender": "male", "height_cm": 180, "weight_kg": 80}
    assert abs(out["avatar"]["height"] - 1.80) < 0.03
    assert out["canvas"]["max"] - out["canvas"]["min"] > 40 and out["canvas"]["colours"] > 10
    assert out["heightInches"] == "70.9"  # 180 cm in inches
    # a slider: the form follows, the avatar grows
    assert out["formAfterSlider"] == "195"
    assert out["heightAfterSlider"] > out["avatar"]["height"] + 0.1
    # a pose preset rotates the bones (and survives reloading the scene with garments)
    assert out["boneBefore"] == [0, 0, 0, 1] and out["boneAfter"] != out["boneBefore"]
    assert out["pose"] == "walking" and out["dressed"]["pose"] == "walking"
    assert out["dressed"]["thigh"] == out["thighAfter"]
    # dressed: avatar + T-shirt + trousers, one skeleton; the customer was saved on the way
    assert out["dressed"]["meshes"] == 3 and out["dressed"]["skinned"] == 3
    assert out["dressed"]["worn"] == out["expectedWorn"]
    assert out["dressed"]["bones"] == BONES
    assert out["dressed"]["customer"] and out["storedId"] == out["dressed"]["customer"]
    assert out["dressedCanvas"]["colours"] > 10
    # delete my data: gone server-side, forgotten client-side
    assert out["customerStatusBefore"] == 200
    assert deleted.status_code == 404
    assert out["storedAfterDelete"] is None
    # after a reload the remembered customer's own measurements are back in the form
    assert out["restored"]["customer"] == out["dressed"]["customer"]
    assert float(out["restored"]["height"]) == pytest.approx(195, abs=0.6)
    assert float(out["restored"]["weight"]) == pytest.approx(80, abs=0.6)
    # the error path: the API's message inline next to the field
    assert "outside the allowed range" in out["inlineError"]
    assert out["lastError"].startswith("height_cm:")
    # a phone width: no horizontal scrolling
    assert out["phoneScrollWidth"] <= 390
    assert not [m for m in out["console"] if m.startswith("pageerror")], out["console"]
