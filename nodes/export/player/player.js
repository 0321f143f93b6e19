// volcap player: plays one rung of a volcap-stream ladder (nodes/export/stream.py) with three.js.
// Per segment: the Draco mesh (connectivity, UVs), the .pos positions (zlib: inflated by the browser), the atlas
// video as texture. URL parameters: rung (default: the first of rungs.json), frame (start frame index),
// still=1 (render that frame once, no controls: what the tests screenshot), silhouette=1 (white on black, no
// texture), camera=<base64 JSON {K, R, t, width, height}> (a volcap camera: x_cam = R X + t, OpenCV axes, pixel
// centres at integer coordinates).
import * as THREE from "three";
import { DRACOLoader } from "three/addons/DRACOLoader.js";
import { OrbitControls } from "three/addons/OrbitControls.js";
import { pinhole } from "./camera.js";

const params = new URLSearchParams(location.search);
const still = params.get("still") === "1", silhouette = params.get("silhouette") === "1";
if (still) document.body.classList.add("still");

async function bytes(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return new Uint8Array(await r.arrayBuffer());
}

async function inflate(data) {
  const stream = new Blob([data]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

function unplanes(b, offset, count, size, signed) {        // byte planes -> values (little endian)
  const out = new Float64Array(count);
  for (let i = 0; i < count; i++) {
    let v = 0;
    for (let k = size - 1; k >= 0; k--) v = v * 256 + b[offset + k * count + i];
    if (signed && v >= 2 ** (8 * size - 1)) v -= 2 ** (8 * size);
    out[i] = v;
  }
  return out;
}

export async function decodePositions(data) {              // the .pos payload -> Float32Array per frame
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const n = view.getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(data.subarray(4, 4 + n)));
  const body = await inflate(data.subarray(4 + n));
  const nf = head.frames, nv = head.vertices, nc = nv * 3;
  const firstSize = head.first === "uint16" ? 2 : 4;
  let at = 0;
  const q = unplanes(body, at, nc, firstSize, false); at += nc * firstSize;
  const motion = new Float64Array((nf - 1) * nc);
  for (let i = 0; i < motion.length; i++) { const v = body[at + i]; motion[i] = v >= 128 ? v - 256 : v; }
  at += motion.length;
  const bv = new DataView(body.buffer, body.byteOffset, body.byteLength);
  for (let e = 0; e < head.escapes; e++) {
    const idx = bv.getUint32(at + 4 * e, true);
    motion[idx] = bv.getInt32(at + 4 * head.escapes + 4 * e, true);
  }
  at += 8 * head.escapes;
  const parent = unplanes(body, at, nv, 4, true);
  const depth = new Int32Array(nv).fill(-1);               // roots first, then by depth
  const order = [];
  for (let v = 0; v < nv; v++) { if (parent[v] < 0) depth[v] = 0; }
  for (let changed = true; changed;) {
    changed = false;
    for (let v = 0; v < nv; v++) if (depth[v] < 0 && depth[parent[v]] >= 0) { depth[v] = depth[parent[v]] + 1; changed = true; }
  }
  const byDepth = Array.from({ length: nv }, (_, v) => v).sort((a, b) => depth[a] - depth[b]);
  for (const v of byDepth) if (parent[v] >= 0) order.push(v);
  const lo = head.box[0], hi = head.box[1], scale = 2 ** head.bits - 1;
  const span = [0, 1, 2].map(a => (hi[a] > lo[a] ? hi[a] - lo[a] : 1));
  const frames = [];
  const cur = Float64Array.from(q);
  const emit = () => {
    const p = new Float32Array(nc);
    for (let i = 0; i < nc; i++) p[i] = lo[i % 3] + cur[i] / scale * span[i % 3];
    frames.push(p);
  };
  emit();
  for (let f = 0; f < nf - 1; f++) {
    const m = motion.subarray(f * nc, (f + 1) * nc);
    for (const v of order) for (let a = 0; a < 3; a++) m[3 * v + a] += m[3 * parent[v] + a];
    for (let i = 0; i < nc; i++) cur[i] += m[i];
    emit();
  }
  return frames;
}

function seek(tex, time) {                                  // a promise: the video shows ``time``, uploaded
  const v = tex.video;
  return new Promise((ok) => {
    const finish = () => { tex.texture.needsUpdate = true; ok(); };
    const done = () => {
      v.removeEventListener("seeked", done); v.removeEventListener("error", done);
      if (v.error || !v.requestVideoFrameCallback) finish();
      else { let once = false; const go = () => { if (!once) { once = true; finish(); } };
             v.requestVideoFrameCallback(go); setTimeout(go, 1000); }
    };
    v.addEventListener("seeked", done);
    v.addEventListener("error", done);
    const set = () => { v.currentTime = time; };
    if (v.readyState >= 1) set(); else v.addEventListener("loadedmetadata", set, { once: true });
  });
}

async function videoTexture(url) {
  // the whole file as a blob: seekable from any static server (python's http.server answers no Range requests)
  const blob = new Blob([await bytes(url)], { type: "video/mp4" });
  const video = document.createElement("video");
  video.muted = true; video.playsInline = true; video.preload = "auto";
  video.src = URL.createObjectURL(blob);
  const texture = new THREE.VideoTexture(video);
  texture.colorSpace = THREE.SRGBColorSpace;               // flipY (the default): UV origin bottom-left, as ours
  return { video, texture };
}

async function loadRung(base, rung) {
  const manifest = JSON.parse(new TextDecoder().decode(await bytes(`${base}/${rung}/manifest.json`)));
  const draco = new DRACOLoader().setDecoderPath("./lib/draco/");
  const segments = [];
  for (const seg of manifest.segments) {
    const drc = await bytes(`${base}/${rung}/${seg.geometry}`);
    const geometry = await new Promise((ok, fail) => draco.parse(drc.buffer, ok, fail));
    const positions = await decodePositions(await bytes(`${base}/${rung}/${seg.positions}`));
    segments.push({ seg, geometry, positions, tex: silhouette ? null : await videoTexture(`${base}/${rung}/${seg.video}`) });
  }
  return { manifest, segments };
}

async function main() {
  const base = ".";
  const rungs = JSON.parse(new TextDecoder().decode(await bytes(`${base}/rungs.json`)));
  const rung = params.get("rung") || rungs[0];
  const select = document.getElementById("rung");
  for (const r of rungs) select.add(new Option(r, r, false, r === rung));
  select.onchange = () => { params.set("rung", select.value); location.search = params.toString(); };
  const { manifest, segments } = await loadRung(base, rung);
  const given = params.get("camera") ? JSON.parse(atob(params.get("camera"))) : null;
  const width = given ? given.width : innerWidth, height = given ? given.height : innerHeight;
  const renderer = new THREE.WebGLRenderer({ antialias: !silhouette, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(width, height);
  renderer.setClearColor(silhouette ? 0x000000 : 0x202124);
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.0));
  const camera = new THREE.PerspectiveCamera(35, width / height, 0.05, 100);
  camera.up.set(0, 0, 1);                                   // the stream's world frame: +Z up, metres
  let controls = null;
  if (given) pinhole(camera, given, 0.05, 100);
  else {
    camera.position.set(0, -4.5, 1.2);
    controls = new OrbitControls(camera, renderer.domElement);
    controls.target.set(0, 0, 0.9);
    controls.update();
  }
  const meshes = segments.map(({ geometry, tex }) => {
    const material = silhouette ? new THREE.MeshBasicMaterial({ color: 0xffffff, side: THREE.DoubleSide })
                                : new THREE.MeshBasicMaterial({ map: tex.texture, side: THREE.DoubleSide });
    const mesh = new THREE.Mesh(geometry, material);
    mesh.frustumCulled = false;
    mesh.visible = false;
    scene.add(mesh);
    return mesh;
  });
  const total = manifest.frames.length;
  const scrub = document.getElementById("scrub"), label = document.getElementById("label");
  scrub.max = String(total - 1);
  let index = Math.min(Math.max(parseInt(params.get("frame") || "0", 10), 0), total - 1);
  let pending = [];
  const show = (k) => {                                     // a promise: the frame's atlas is in the texture
    pending = [];
    let start = 0;
    segments.forEach((s, i) => {
      const local = k - start;
      const inside = local >= 0 && local < s.seg.frames;
      meshes[i].visible = inside;
      if (inside) {
        s.geometry.setAttribute("position", new THREE.BufferAttribute(s.positions[local], 3));
        s.geometry.attributes.position.needsUpdate = true;
        if (s.tex) pending.push(seek(s.tex, (local + 0.5) / manifest.fps));
      }
      start += s.seg.frames;
    });
    scrub.value = String(k);
    label.textContent = `frame ${manifest.frames[k]} (${k + 1}/${total}) ${manifest.rung}`;
    return Promise.all(pending);
  };
  const first = show(index);
  let playing = false, last = performance.now();
  document.getElementById("play").onclick = (e) => { playing = !playing; e.target.textContent = playing ? "pause" : "play"; };
  scrub.oninput = () => { index = parseInt(scrub.value, 10); show(index); };
  const frame = (now) => {
    if (playing && now - last >= 1000 / manifest.fps) { index = (index + 1) % total; show(index); last = now; }
    if (controls) controls.update();
    renderer.render(scene, camera);
    if (!still) requestAnimationFrame(frame);
  };
  if (still) {
    await first;
    for (const s of segments) {
      if (s.tex && s.tex.video.error) throw new Error(`atlas video ${s.seg.video}: ${s.tex.video.error.message || "cannot be decoded"}`);
    }
    renderer.render(scene, camera);
    document.title = "ready";
  } else requestAnimationFrame(frame);
}

main().catch((err) => { document.title = "error"; document.body.insertAdjacentHTML("beforeend", `<pre id="error">${err}</pre>`); });
