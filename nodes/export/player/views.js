// volcap view-dependent texture viewer: one frame's textured mesh (mesh.bin, base.png) and its layers (export.views:
// layer_<k>.png, view_<k>.png, cameras.json), blended per fragment by the viewing direction exactly as
// nodes/common/viewlayers.py layer_weights says: w_k = exp(-(a_k / sigma)^2) / a_k over the angle a_k between the
// ray to the eye and the ray to layer k's camera, the atlas (base) counting as a layer at angle sigma.
// URL parameters: still=1 (render once, no controls: what the tests screenshot), static=1 (the atlas alone),
// camera=<base64 JSON {K, R, t, width, height}> (a volcap camera, see camera.js). World frame: +Z up, metres.
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";
import { pinhole } from "./camera.js";

const params = new URLSearchParams(location.search);
const still = params.get("still") === "1";
if (still) document.body.classList.add("still");

async function bytes(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return new Uint8Array(await r.arrayBuffer());
}

async function pixels(url) {                                // a PNG's RGBA bytes, as stored (no colour management)
  const bmp = await createImageBitmap(new Blob([await bytes(url)], { type: "image/png" }),
                                      { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  const canvas = new OffscreenCanvas(bmp.width, bmp.height);
  const g = canvas.getContext("2d", { willReadFrequently: true });
  g.drawImage(bmp, 0, 0);
  return { width: bmp.width, height: bmp.height, rgba: g.getImageData(0, 0, bmp.width, bmp.height).data };
}

async function loadMesh(url) {                              // mesh.bin: uint32 n, JSON header, float32 xyz, uv, uint32 faces
  const b = await bytes(url);
  const n = new DataView(b.buffer).getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(b.subarray(4, 4 + n)));
  let at = 4 + n;
  const take = (Type, count) => { const a = new Type(b.buffer.slice(at, at + 4 * count)); at += 4 * count; return a; };
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(take(Float32Array, 3 * head.vertices), 3));
  geometry.setAttribute("uv", new THREE.BufferAttribute(take(Float32Array, 2 * head.vertices), 2));
  geometry.setIndex(new THREE.BufferAttribute(take(Uint32Array, 3 * head.faces), 1));
  geometry.computeBoundingBox();
  return geometry;
}

const vertexShader = `
varying vec2 vUv;
varying vec3 vWorld;
void main() {
  vUv = uv;
  vec4 w = modelMatrix * vec4(position, 1.0);
  vWorld = w.xyz;
  gl_Position = projectionMatrix * viewMatrix * w;
}`;

const fragmentShader = `
precision highp float;
precision highp sampler2DArray;
precision highp usampler2DArray;
uniform sampler2D base;
uniform sampler2DArray layers;
uniform usampler2DArray views;
uniform sampler2D centres;
uniform float sigma;
uniform int K;
uniform int S;
uniform uint none;
uniform bool useLayers;
varying vec2 vUv;
varying vec3 vWorld;
layout(location = 0) out vec4 fragColor;
void main() {
  vec2 st = vec2(vUv.x, 1.0 - vUv.y);                       // image rows top down, as the atlas PNGs
  vec3 col = texture(base, st).rgb;
  if (useLayers) {
    vec3 toEye = normalize(cameraPosition - vWorld);
    float wb = exp(-1.0) / sigma;
    vec3 sum = wb * col;
    float total = wb;
    ivec2 tx = clamp(ivec2(floor(st * float(S))), ivec2(0), ivec2(S - 1));   // camera ids do not interpolate
    for (int k = 0; k < K; k++) {
      uint id = texelFetch(views, ivec3(tx, k), 0).r;
      if (id == none) continue;
      vec3 c = texelFetch(centres, ivec2(int(id), 0), 0).xyz;
      float a = acos(clamp(dot(normalize(c - vWorld), toEye), -1.0, 1.0));
      float w = exp(-(a / sigma) * (a / sigma)) / max(a, 1e-4);
      sum += w * texture(layers, vec3(st, float(k))).rgb;
      total += w;
    }
    col = sum / total;
  }
  fragColor = vec4(col, 1.0);
}`;

function linear(texture) {                                  // bilinear, no mipmaps, raw values (what render_layers samples)
  texture.minFilter = texture.magFilter = THREE.LinearFilter;
  texture.generateMipmaps = false;
  texture.colorSpace = THREE.NoColorSpace;
  texture.needsUpdate = true;
  return texture;
}

async function main() {
  const doc = JSON.parse(new TextDecoder().decode(await bytes("./cameras.json")));
  const K = doc.layers;
  const geometry = await loadMesh("./mesh.bin");
  const basePx = await pixels("./base.png");
  const S = basePx.width;
  const layerData = new Uint8Array(S * S * 4 * K), viewData = new Uint8Array(S * S * Math.max(K, 1));
  for (let k = 0; k < K; k++) {
    const l = await pixels(`./layer_${k}.png`), v = await pixels(`./view_${k}.png`);
    if (l.width !== S || v.width !== S) throw new Error(`layer ${k} is not ${S}x${S} like base.png`);
    layerData.set(l.rgba, k * S * S * 4);
    for (let i = 0; i < S * S; i++) viewData[k * S * S + i] = v.rgba[4 * i];
  }
  const layers = linear(new THREE.DataArrayTexture(layerData, S, S, K));
  const views = new THREE.DataArrayTexture(viewData, S, S, Math.max(K, 1));
  views.format = THREE.RedIntegerFormat;
  views.internalFormat = "R8UI";
  views.minFilter = views.magFilter = THREE.NearestFilter;
  views.generateMipmaps = false;
  views.unpackAlignment = 1;
  views.needsUpdate = true;
  const c = new Float32Array(4 * doc.centres.length);
  doc.centres.forEach((p, i) => c.set([p[0], p[1], p[2], 1], 4 * i));
  const centres = new THREE.DataTexture(c, doc.centres.length, 1, THREE.RGBAFormat, THREE.FloatType);
  centres.minFilter = centres.magFilter = THREE.NearestFilter;
  centres.needsUpdate = true;
  const material = new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3, vertexShader, fragmentShader, side: THREE.DoubleSide,
    uniforms: { base: { value: linear(new THREE.DataTexture(basePx.rgba, S, S)) }, layers: { value: layers },
                views: { value: views }, centres: { value: centres }, sigma: { value: doc.sigma }, K: { value: K },
                S: { value: S }, none: { value: doc.none }, useLayers: { value: params.get("static") !== "1" } } });
  const given = params.get("camera") ? JSON.parse(atob(params.get("camera"))) : null;
  const width = given ? given.width : innerWidth, height = given ? given.height : innerHeight;
  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(width, height);
  renderer.setClearColor(0x000000);
  let shaderError = null;                                   // a shader that does not compile is an error, not black
  renderer.debug.onShaderError = (gl, program, vs, fs) => {
    shaderError = `${gl.getShaderInfoLog(vs) || ""} ${gl.getShaderInfoLog(fs) || ""} ${gl.getProgramInfoLog(program) || ""}`;
  };
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  const mesh = new THREE.Mesh(geometry, material);
  mesh.frustumCulled = false;
  scene.add(mesh);
  const camera = new THREE.PerspectiveCamera(35, width / height, 0.01, 100);
  camera.up.set(0, 0, 1);
  let controls = null;
  if (given) pinhole(camera, given, 0.01, 100);
  else {                                                    // orbit from the first capture camera
    const centre = geometry.boundingBox.getCenter(new THREE.Vector3());
    camera.position.set(...doc.centres[0]);
    controls = new OrbitControls(camera, renderer.domElement);
    controls.target.copy(centre);
    controls.update();
  }
  const box = document.getElementById("layers"), label = document.getElementById("label");
  box.checked = material.uniforms.useLayers.value;
  box.onchange = () => { material.uniforms.useLayers.value = box.checked; };
  label.textContent = `${K} layers from ${doc.names.length} cameras, ${S}x${S}`;
  renderer.render(scene, camera);
  if (shaderError) throw new Error(`the layer shader: ${shaderError}`);
  if (still) { document.title = "ready"; return; }
  const frame = () => { controls.update(); renderer.render(scene, camera); requestAnimationFrame(frame); };
  requestAnimationFrame(frame);
}

main().catch((err) => { document.title = "error"; document.body.insertAdjacentHTML("beforeend", `<pre id="error">${err}</pre>`); });
