// A volcap camera as a three.js camera (shared by the stream player and the view-dependent viewer).
import * as THREE from "three";

// cam = {K, R, t, width, height}: x_cam = R X + t, OpenCV axes (x right, y down, z forward)
export function pinhole(camera, cam, near, far) {
  // volcap's pixel centres are at integer coordinates (Cameras.project), WebGL's at i + 0.5: shift by half a pixel
  const [fx, s] = cam.K[0], cx = cam.K[0][2] + 0.5, fy = cam.K[1][1], cy = cam.K[1][2] + 0.5, W = cam.width, H = cam.height;
  camera.projectionMatrix.set(2 * fx / W, -2 * s / W, 1 - 2 * cx / W, 0,
                              0, 2 * fy / H, 2 * cy / H - 1, 0,
                              0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
                              0, 0, -1, 0);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  const R = cam.R, t = cam.t;                               // view = diag(1, -1, -1) [R | t]
  const view = new THREE.Matrix4().set(R[0][0], R[0][1], R[0][2], t[0],
                                       -R[1][0], -R[1][1], -R[1][2], -t[1],
                                       -R[2][0], -R[2][1], -R[2][2], -t[2],
                                       0, 0, 0, 1);
  camera.matrixAutoUpdate = false;
  camera.matrixWorldInverse.copy(view);
  camera.matrixWorld.copy(view).invert();
}
