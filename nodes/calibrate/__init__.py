"""calibrate: a camera rig from checkerboard images (intrinsics per camera, extrinsics from boards seen by several
cameras at once, one bundle adjustment over everything)."""
