"""quatrack.viewsets — the object model: what training makes and recognition reads.

Entry points:
- ``spec.load_spec(path) -> ObjectSpec`` (poses as :class:`quatrack.tracking.pose.Pose`,
  ``spec.parse_pose`` for the pose forms of the contract); ``camera.load_camera(path)`` /
  ``camera.camera_from_dict(obj)`` with ``camera.check_plausible``.
- ``train.train_object(spec) -> ObjectModel``: RFCH model (:mod:`.rfch`) + SIFT viewsets
  (:mod:`.viewset`, :mod:`.features`) of the registered views and of novel views (:mod:`.novel`);
  ``batch.train_many`` for several specs (local processes or Ray).
- ``store.save_model`` / ``store.load_model`` / ``store.list_models`` / ``store.delete_model``:
  the atomic model store (``store.resolve_store(arg)`` for ``--store``).
- :mod:`.mesh` (PLY/OBJ through trimesh) and :mod:`.render` (z-buffer, ray casting, lifting
  keypoints onto the mesh), shared by training, verification and the tracker's mesh-born points.
"""
