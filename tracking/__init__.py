"""tracking: rotations, measurement models, motion models and the quaternion pose filter of Ude (1999).

Pure numpy/scipy (and numba for one hot loop, :mod:`.jit`): no I/O, no OpenCV, no HTTP.
"""
