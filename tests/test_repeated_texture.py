"""Texture repeated on a side no photo shows: a wrong pose carried by one face must be refused.

The zoo's boxes are textured with overlapping crops of one photograph, so a side the training
photo never showed carries much of the texture of a side it did. Seen from that unseen side, the
matches are all right as descriptors and all wrong as points: they hold the learned face where
the image shows the other one, 60–90° off, with a tight covariance and no rival consensus. What
gives it away is the rest of the outline: the pose's other edges are not in the image."""

import cv2
import numpy as np
import pytest
from dataclasses import replace

from quatrack.recognition.locate import LocateParams, locate
from quatrack.recognition.pose import PoseParams
from quatrack.testing import scenes as S
from quatrack.testing import zoo as Z
from quatrack.viewsets.spec import load_spec
from quatrack.viewsets.train import train_object

CAM = Z.zoo_camera()


@pytest.fixture(scope="module")
def wide_box(tmp_path_factory):
    """The wide box (20 × 14 × 9 cm) trained from one colour photo, as `bench locate --zoo` trains it."""
    cv2.setRNGSeed(0)
    spec = load_spec(Z.write_spec("wide-box-cm", tmp_path_factory.mktemp("wide"), 1, grey=False, seed=0,
                                  backgrounds=Z.real_backgrounds()))
    return train_object(spec), spec


def _unseen_side_scene(spec, seed: int):
    """The box turned 50–75° away from its photo, 30–65 % out of the frame (the scene's seed)."""
    rng = np.random.default_rng(seed)
    angle, outside = rng.uniform(50, 75), rng.uniform(0.3, 0.65)
    return Z.random_scene(rng, Z.textured("wide-box-cm"), CAM, spec.views[0].pose, Z.real_backgrounds(),
                          angle, outside, False)


def _wrong(r, pose, mesh) -> bool:
    if not r.found:
        return False
    dt, dr = S.pose_errors(r.t, r.q_wxyz, pose, mesh)
    return dt > 0.05 * mesh.extent or dr > 5.0


def test_a_pose_of_repeated_texture_without_the_rest_of_its_outline_is_refused(wide_box):
    """The box seen from below, half out of the frame (scene 254): its matches hold the learned
    face 60 % of the diameter and ~90° off. Until session 39 that pose passed every check but
    the one-face rule (``one_face_edge_agreement``: a whole visible edge missing and a marginal
    outline) and the texture's evidence: the far outline of faces seen at a grazing angle
    counted as hidden, so the pose's missing edges went unseen. With the whole outline the
    edges' agreement refuses it on its own (44 % agree), and none of 400 such scenes (seeds
    0–399) traps ``locate`` without the rule and the texture any more."""
    model, spec = wide_box
    sc = _unseen_side_scene(spec, 254)
    no_rule = replace(PoseParams(), one_face_edge_agreement=None)
    blind = locate(sc.image, CAM, model, LocateParams(pose=no_rule, min_texture_ncc=0.0))
    assert not _wrong(blind, sc.pose, model.mesh)
    assert not blind.found and "edges" in blind.reason and blind.verification["edge_agreement"] < 0.6
    for params in (LocateParams(), LocateParams(pose=no_rule)):
        assert not _wrong(locate(sc.image, CAM, model, params), sc.pose, model.mesh)


def test_the_rule_leaves_right_poses_of_the_box_alone(wide_box):
    """Right poses of the same box (near its photo's view, up to 40 % out of the frame, often on
    one face) pass as before: the rule asks for a whole visible edge missing *and* a marginal
    outline."""
    model, spec = wide_box
    found = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        sc = Z.random_scene(rng, Z.textured("wide-box-cm"), CAM, spec.views[0].pose, Z.real_backgrounds(),
                            rng.uniform(0, 20), rng.uniform(0.0, 0.4), False)
        off = locate(sc.image, CAM, model, LocateParams(pose=replace(PoseParams(), one_face_edge_agreement=None)))
        on = locate(sc.image, CAM, model)
        assert on.found == off.found and not _wrong(on, sc.pose, model.mesh)
        found += on.found
    assert found >= 4
