"""Ground truth to test and measure against: objects rendered at known poses.

Tests and benchmarks share these fixtures, and they live here, in the product's namespace but
outside every pipeline layer, so that neither ``tests/`` nor ``bench/`` owns what the other needs
and a non-editable install (the Dockerfile's) still finds them:

- :mod:`.scenes`: the bundled cookie box (``example_store``, ``example_model``, ``Renderer``),
  real room backgrounds from ``box.mp4`` with the box inpainted away (stored as files:
  :mod:`.backgrounds`), random scenes and ``pose_errors`` (centre distance and rotation angle
  to the truth);
- :mod:`.zoo`: eight more objects (boxes, cubes, a cylinder, a prism; meshes in mm, cm and m)
  textured from real photographs, their training specs and degraded scenes;
- :mod:`.sequences`: smooth trajectories and rendered video sequences with their true poses;
- :mod:`.scans`: a scan's mesh of a known object (its CAD mesh subdivided, optionally jittered);
- :mod:`.balancer`: Debian's nginx started in front of local replicas (deployment test, bench);
- :mod:`.loopback`: a free port, addresses and the start-up wait of anything run on loopback.

No pipeline layer (tracking, viewsets, recognition) imports it (``tests/test_layering.py``); the
service's loopback runners (``service.server``, for tests, the demo and the bench) use :mod:`.loopback`.
"""
