"""Domain code shared by the stages: cameras, calibration readers, port types and previews, silhouettes
and the visual hull's vote, the rasterizer, mesh operations. Stages import this and nodegraph, never
each other."""

import os

from nodegraph import clrt
from nodegraph.worker import on_worker_start


@on_worker_start
def _opencv_threads():
    if os.environ.get("VOLCAP_CV_THREADS"):
        import cv2

        cv2.setNumThreads(int(os.environ["VOLCAP_CV_THREADS"]))


on_worker_start(clrt.context)  # the OpenCL context, once per worker process
