"""quatrack.viewsets — the object model: spec and camera parsing, mesh, rendering, SIFT viewsets,
RFCH, novel views, the atomic model store and the training logic.

Public entry points used by recognition (issue 4):
- ``store.load_model(store, name) -> ObjectModel`` (``store.resolve_store(arg)`` for ``--store``);
- ``viewset.extract_query_features(image, mask, viewset.params_from_manifest(model.manifest))``;
- ``rfch.label_image(image, model.rfch)``, ``rfch.cooccurrence(labels, mask, n, d)``, ``rfch.chi2``;
- ``camera.load_camera(path)`` / ``camera.camera_from_dict(obj)``, ``spec.parse_pose(obj)``.
"""
