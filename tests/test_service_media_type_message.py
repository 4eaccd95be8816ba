"""The 415 says which content types are taken: it said "the raw image with an image/* content
type", while ``application/octet-stream`` is taken too (the format is read from the bytes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from quatrack.service.app import create_app
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

Q = "fx=669.7&fy=667.8&cx=320&cy=240"


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(Settings(store=example_store(), workers=1, threads=1, model_poll_s=0))) as c:
        yield c


def test_the_refusal_names_every_type_taken_and_each_is_taken(client):
    img = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    r = client.post(f"/v1/objects/cookie-box/pose?{Q}", content=img, headers={"content-type": "text/plain"})
    assert r.status_code == 415, r.text
    msg = r.json()["error"]["message"]
    assert "'text/plain'" in msg and "application/octet-stream" in msg and "image/*" in msg, msg
    for ctype in ("application/octet-stream", "image/jpeg"):
        r = client.post(f"/v1/objects/cookie-box/pose?{Q}", content=img, headers={"content-type": ctype})
        assert r.status_code == 200, (ctype, r.text)
