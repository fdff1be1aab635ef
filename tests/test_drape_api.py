"""The drape in the garment build (issue 43), end to end in process: with ``TRYON_DRAPE`` on, a
``.mhclo`` upload is draped at its own size (as bound to the mean example avatar) on every example
avatar before its basis is built; the record carries its fabric. Slow: 65 drapes."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.model.formats.gltf_read import read_glb
from service.settings import Settings
from tests.bench.common import shared_data_dir
from tests.harness import RETAILERS, redis_db, redis_url

pytestmark = pytest.mark.slow

KEY = {"X-API-Key": RETAILERS["acme"]}
HAT = shared_data_dir() / "makehuman_clothes" / "fedora01"


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("drape"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="", TRYON_DRAPE=True, TRYON_DRAPE_POPULATION=8,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def test_mhclo_upload_is_draped_on_every_example(client: TestClient) -> None:
    files = {"mhclo": ("fedora.mhclo", (HAT / "fedora.mhclo").read_bytes()),
             "obj": ("fedora.obj", (HAT / "fedora.obj").read_bytes())}
    r = client.post("/v1/garments", data={"name": "Hat", "fabric": "woven", "layer": "2"}, files=files, headers=KEY)
    assert r.status_code == 201, r.text
    hat = r.json()
    assert hat["fabric"] == "woven" and hat["status"] == "ready" and hat["n_components"] == 32
    # the basis was built from draped examples: the mean garment is not the bound one (the hat,
    # modelled floating over the head, settles onto it under gravity), and it stays outside
    ctx = client.app.state.context
    basis = ctx.bases.load(hat["id"], hat["etag"])
    ex = ctx.garments.examples
    from service.application.uploads import read_mhclo_layout

    binding, faces, _ = read_mhclo_layout(ctx.model, files["mhclo"][1], files["obj"][1])
    bound = binding.fit(ex.vertices[0])
    moved = np.linalg.norm(np.asarray(basis.g) - bound, axis=1)
    assert np.median(moved) > 1e-3 and moved.max() < 0.10
    from service.model.geometry.mesh import winding_numbers

    body = ctx.model.body_vertices(ex.vertices[0]).astype(np.float64)
    assert (winding_numbers(np.asarray(basis.g, np.float64), body, ctx.model.body_faces) < 0.5).mean() > 0.99
    glb = read_glb(client.get(f"/v1/garments/{hat['id']}/basis.glb").content)
    assert glb["meshes"][0]["name"] == "Hat"
