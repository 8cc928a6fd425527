// The viewer page: streams a run's splats from the server, draws them with WebGL2, and wires
// the controls (sets, overlays, tau, exposure, LoD). Camera navigation (navigation.js), time
// (timeline.js), editing (editing.js), the export panel (export-panel.js), drawing settings and
// the URL (view-settings.js) and local files (local-view.js) are mixed into `Viewer`.

import { api, openStream, withToken } from "./api.js";
import { parseBuffer } from "./buffers.js";
import { FLAG_DYNAMIC, packSet, textureRows, TEX_WIDTH, SPLATS_PER_ROW } from "./pack.js";
import { SplatRenderer, nearestInTime, shakeSweep } from "./renderer.js";
import { OrbitCamera, cameraCenter, focusDepth, intrinsics, orbitAtDepth } from "./camera.js";
import { drawHistogram } from "./chart.js";
import { $, esc } from "./dom.js";
import { arrowScale, arrowSegments } from "./arrows.js";
import { navigation } from "./navigation.js";
import { editing } from "./editing.js";
import { exportPanel } from "./export-panel.js";
import { viewSettings } from "./view-settings.js";
import { localView } from "./local-view.js";
import { timeline } from "./timeline.js";

export class Viewer {
  constructor(runId) {
    this.runId = runId;
    this.canvas = $("canvas");
    this.worker = new Worker(new URL("./sort-worker.js", import.meta.url), { type: "module" });
    this.worker.onmessage = (e) => this.onSorted(e.data);
    this.sortId = 0;
    this.sortPending = null;
    this.static = null;
    this.dynamic = null;
    this.t = 0;
    this.exposure = 0;
    this.lod = null;
    this.show = 3;
    this.overlay = 0;
    this.stride = 4;
    this.arrows = false;
    this.playing = false;
    this.speed = 1;
    this.selected = new Set();
    this.frameCount = 0;
    this.dirty = true;
    this.seq = 0;
    this.waiters = [];
    this.fixedSize = null;
  }

  async start() {
    this.loading("loading the run…");
    this.renderer = await SplatRenderer.create(this.canvas);
    this.meta = await api(`/api/runs/${this.runId}`);
    if (!this.meta.has_model) {
      this.loading(null);
      throw new Error(`run ${this.runId} has no model yet (${this.meta.status})`);
    }
    this.loading("connecting…");
    const m = this.meta;
    this.initCamera();
    this.initControls();
    this.restoreViewState();
    this.connect();
    this.resize();
    window.addEventListener("resize", () => this.resize());
    this.looping = true;
    this.mouseReady = true;
    requestAnimationFrame((now) => this.loop(now));
  }

  // ------------------------------------------------------------------ camera

  initCamera() {
    const frames = this.meta.frames.filter((f) => f.split === "train");
    const f = frames[0] || this.meta.frames[0];
    const vm = f ? f.viewmat.flat() : [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1];
    this.viewmat = vm;
    const c = cameraCenter(vm);
    const fwd = [vm[8], vm[9], vm[10]];
    const up = f ? [-vm[4], -vm[5], -vm[6]] : [0, -1, 0];
    // A first guess at the pivot (the origin's distance ahead); `pivotOnContent` moves it onto
    // the Gaussians once they arrive.
    const dist = Math.hypot(...c) || 3;
    const target = [c[0] + dist * fwd[0], c[1] + dist * fwd[1], c[2] + dist * fwd[2]];
    this.orbit = OrbitCamera.fromViewmat(vm, target, up);
    this.up = up;
    this.mode = "orbit";
    this.fovFrame = f;
    this.pivotSet = false;
    // How far the training cameras travelled (the largest side of their centres' bounding box):
    // views much further from their path than this show what no input saw.
    const centres = frames.map((fr) => cameraCenter(fr.viewmat.flat()));
    this.cameraSpan = centres.length > 1
      ? Math.max(...[0, 1, 2].map((k) => Math.max(...centres.map((p) => p[k])) - Math.min(...centres.map((p) => p[k]))))
      : Infinity;
  }

  // Open on the first training camera's view, orbiting about the median depth of what it
  // sees, so that turning keeps the scene in frame. Once, before the user moves the view.
  pivotOnContent(set) {
    if (this.pivotSet || !set || !set.count) return;
    this.pivotSet = true;
    const vm = this.orbit.viewmat();
    const depth = focusDepth(vm, set.positions, set.count);
    // A camera that filmed from inside the scene (a corridor, a room) has content close beside
    // it: pivoting at the content's depth would swing it through the walls. The pivot stays
    // within twice the distance the input cameras travelled, so turning keeps near their path.
    if (depth !== null) this.orbit = orbitAtDepth(vm, Math.min(depth, 2 * this.cameraSpan), this.up);
  }

  intrinsics() {
    if (this.fixedK) return this.fixedK;
    const w = this.canvas.width, h = this.canvas.height;
    if (this.fovDeg) return intrinsics(w, h, this.fovDeg);  // the field-of-view control
    const f = this.fovFrame;
    if (f) {  // the training camera's field of view, fitted to the canvas
      const fovx = 2 * Math.atan(f.width / (2 * f.K[0][0])) * 180 / Math.PI;
      return intrinsics(w, h, fovx);
    }
    return intrinsics(w, h, 60);
  }

  resize() {
    if (this.fixedSize) return;
    // Device pixels on a HiDPI screen (sharp splats), at most two per CSS pixel: the splats'
    // blending cost grows with the pixel count.
    const r = this.canvas.getBoundingClientRect(), dpr = Math.min(2, window.devicePixelRatio || 1);
    this.canvas.width = Math.max(16, Math.round(r.width * dpr));
    this.canvas.height = Math.max(16, Math.round(r.height * dpr));
    this.dirty = true;
    this.requestSort();
  }

  setViewmat(vm) {
    this.viewmat = vm;
    this.dirty = true;
    this.requestSort();
  }

  // ------------------------------------------------------------------ streaming

  connect() {
    this.ws = openStream(this.runId);
    this.ws.onopen = () => this.subscribe();
    this.ws.onmessage = (e) => (typeof e.data === "string" ? this.onJSON(JSON.parse(e.data)) : this.onBuffer(e.data));
    // 4401 (token), 4404 (run), 4008 (slow reader) come with a reason worth showing.
    this.ws.onclose = (e) => {
      this.loading(null);
      this.status(e.reason ? `connection closed (${e.code}): ${e.reason}` : "connection closed");
    };
  }

  subscribe() {
    this.static = null;
    this.dynamic = null;
    this.loadingProgress();
    this.ws.send(JSON.stringify({ type: "subscribe", lod: this.lod, velocity: true, sh: this.meta.sh_degree > 0 }));
    this.requestTime();
  }

  requestTime() {
    if (!this.ws || this.ws.readyState !== 1) return;
    this.seq += 1;
    this.ws.send(JSON.stringify({ type: "time", t: this.t, exposure: this.exposure, seq: this.seq }));
  }

  onJSON(msg) {
    if (msg.type === "decomposition") {
      this.meta.decomposition = msg;
      this.meta.tau = msg.tau;
      this.updateCounts();
      const waiting = this.waiters.filter((w) => w.kind === "decomposition");
      waiting.forEach((w) => w.resolve(msg));
      this.waiters = this.waiters.filter((w) => w.kind !== "decomposition");
    } else if (msg.type === "error") {
      this.status(`server: ${msg.message}`);
    }
  }

  // The cold-open steps, shown over the canvas until the first frame has both sets (null hides).
  loading(text) {
    const el = $("loading");
    el.hidden = !text;
    el.textContent = text || "";
  }

  loadingProgress() {
    if (this.static && this.dynamic) return this.loading(null);
    const got = (set, name) => (set ? `${name} ${set.count.toLocaleString()} ✓` : `${name}…`);
    this.loading(`receiving Gaussians: ${got(this.static, "static")} · ${got(this.dynamic, "dynamic")}`);
  }

  onBuffer(data) {
    const set = parseBuffer(data);
    if (set.header.kind === "sh") {  // the level's view-dependent colour, by Gaussian index
      this.renderer.uploadSH(set);
      this.dirty = true;
      return;
    }
    if (set.header.kind === "static") {
      this.static = set;
      this.pivotOnContent(set);
    } else {
      if (set.header.version !== (this.static && this.static.header.version)) {
        // arrived before the matching static set: keep it, it will be drawn with it
      }
      this.dynamic = set;
      this.lastDynamicT = set.header.t;
      this.lastDynamicExposure = set.header.exposure;
    }
    this.loadingProgress();
    this.rebuild();
  }

  rebuild() {
    const s = this.static, d = this.dynamic;
    const ns = s ? s.count : 0, nd = d ? d.count : 0;
    const n = ns + nd;
    const rows = textureRows(n);
    if (!this.words || this.words.length !== rows * TEX_WIDTH * 4) {
      this.words = new Uint32Array(rows * TEX_WIDTH * 4);
      this.packedStatic = null;
    }
    const staticChanged = s !== this.packedStatic;
    if (s && staticChanged) packSet(this.words, 0, s, 0, this.selected);
    if (d) packSet(this.words, ns, d, FLAG_DYNAMIC, this.selected);
    this.renderer.upload(this.words, rows, n, staticChanged ? 0 : Math.floor(ns / SPLATS_PER_ROW));
    this.packedStatic = s;
    this.positions = new Float32Array(3 * n);
    if (s) this.positions.set(s.positions, 0);
    if (d) this.positions.set(d.positions, 3 * ns);
    this.buildArrows();
    this.requestSort(true);
  }

  buildArrows() {
    const d = this.dynamic;
    if (!d || !d.velocity) { this.renderer.setLines(new Float32Array(0)); return; }
    const [scale, frames] = arrowScale(d.positions, d.velocity, d.count, this.meta.dt || 0.02);
    const vm = this.currentViewmat();  // the head strokes face the camera of this moment
    this.renderer.setLines(arrowSegments(d.positions, d.velocity, d.count, Math.max(1, this.stride), scale,
                                         [vm[8], vm[9], vm[10]]));
    $("arrow-scale").textContent = `arrows: ${frames.toFixed(frames < 10 ? 1 : 0)} frame intervals of motion`;
  }

  requestSort(force = false) {
    if (!this.positions) return;
    const vm = this.currentViewmat();
    const row = [vm[8], vm[9], vm[10], vm[11]];
    if (!force && this.lastRow && row.every((v, i) => Math.abs(v - this.lastRow[i]) < 1e-4)) return;
    this.lastRow = row;
    this.sortId += 1;
    const positions = this.positions.slice();
    this.sortPending = this.sortId;
    this.worker.postMessage({ positions, count: positions.length / 3, viewRow: row, id: this.sortId }, [positions.buffer]);
  }

  onSorted({ order, id }) {
    if (id !== this.sortId) return;  // a newer sort is on its way
    this.renderer.setOrder(order);
    this.sortPending = null;
    this.dirty = true;
  }

  currentViewmat() {
    if (this.mode === "orbit" && !this.fixedView) return this.orbit.viewmat();
    return this.viewmat;
  }

  // ------------------------------------------------------------------ the frame loop

  loop(now) {
    // A slow frame (a sort, a new buffer) advances time and the fly camera by at most a tenth of
    // a second, so that playback and flying do not jump.
    const dt = this.lastNow ? Math.min(0.1, (now - this.lastNow) / 1000) : 0;
    if (this.playing) this.advancePlayback(dt);
    this.lastNow = now;
    this.fly(dt);
    if (this.dirty && this.sortPending === null) {
      const viewmat = this.currentViewmat();
      this.renderer.draw({ viewmat, K: this.intrinsics(), show: this.show, overlay: this.overlay,
                           stride: this.stride, arrows: this.arrows, sh: this.viewDependent,
                           background: this.background, shake: this.shake() });
      this.saveViewState();
      this.dirty = false;
      this.frameCount += 1;
      this.resolveWaiters();
      this.updateInputFrame();
    }
    requestAnimationFrame((n) => this.loop(n));
  }

  // "As captured": the camera's shake the run learned at the training frame nearest in time,
  // for the static splats (the server blurs the dynamic set it sends); null when sharp.
  shake() {
    const records = this.meta?.blur?.camera_motion;
    if (!(this.exposure > 0) || !records) return null;
    return shakeSweep(nearestInTime(records, this.t), this.meta.dt, this.exposure);
  }

  resolveWaiters() {
    const keep = [];
    for (const w of this.waiters) {
      if (w.kind === "frame" && w.ready()) w.resolve(this.frameCount); else keep.push(w);
    }
    this.waiters = keep;
  }

  // Resolves once a frame has been drawn with the current time's dynamic set.
  drawn() {
    return new Promise((resolve) => {
      const t = this.t, exposure = this.exposure;
      this.waiters.push({ kind: "frame", resolve,
        ready: () => this.static && this.sortPending === null
          && (this.local || (this.dynamic && Math.abs(this.lastDynamicT - t) < 1e-9 && this.lastDynamicExposure === exposure)) });
      this.dirty = true;
    });
  }

  // ------------------------------------------------------------------ controls

  initControls() {
    const m = this.meta;
    $("time").oninput = (e) => this.setTime(e.target.value / 1000, true);
    $("play").onclick = () => this.togglePlay();
    $("reset-view").onclick = () => this.resetView();
    $("frame-scene").onclick = () => this.frameScene();
    // The slider's arrow keys step a frame, not a thousandth of the clip.
    $("time").onkeydown = (e) => {
      if (e.key !== "ArrowLeft" && e.key !== "ArrowRight") return;
      e.preventDefault();
      this.stepFrame(e.key === "ArrowRight" ? 1 : -1);
    };
    $("speed").onchange = (e) => (this.speed = parseFloat(e.target.value));
    $("step-back").onclick = () => this.stepFrame(-1);
    $("step-fwd").onclick = () => this.stepFrame(1);
    $("show-static").onchange = $("show-dynamic").onchange = () => {
      this.show = ($("show-static").checked ? 1 : 0) | ($("show-dynamic").checked ? 2 : 0);
      this.dirty = true;
    };
    $("overlay").onchange = (e) => {
      this.overlay = parseInt(e.target.value, 10);
      $("overlay-legend").dataset.overlay = this.overlay;  // the legend of the chosen overlay (CSS)
      this.dirty = true;
    };
    $("arrows").onchange = (e) => { this.arrows = e.target.checked; this.dirty = true; };
    $("density").oninput = (e) => {
      this.stride = parseInt(e.target.value, 10);
      $("density-label").textContent = e.target.value;
      this.buildArrows();
      this.dirty = true;
    };
    // Say which exposure "as captured" renders with and what blur the run learned; with no
    // exposure it would change nothing.
    const captured = document.querySelector('#exposure option[value="captured"]');
    const learned = m.blur ? (m.blur.objects || m.blur.camera_motion ? "" : ", no learned blur") : "";
    captured.textContent = `as captured (exposure ${Number(m.exposure || 0).toFixed(2)}${learned})`;
    captured.disabled = !(m.exposure > 0);
    $("exposure-note").textContent = m.blur ? m.blur.note : "";
    $("exposure").onchange = (e) => {
      this.exposure = e.target.value === "captured" ? m.exposure : 0;
      this.requestTime();
    };
    const lod = $("lod");
    lod.innerHTML = m.levels.map((l) => `<option value="${esc(l.level)}">LoD ${esc(l.level)} (${esc(Number(l.gaussians).toLocaleString())})</option>`).join("");
    lod.value = String(m.lod_levels);
    lod.onchange = (e) => { this.lod = parseInt(e.target.value, 10); this.selected.clear(); this.subscribe(); };
    const tau = $("tau");
    tau.value = Math.log10(m.tau);
    let tauTimer = null;
    tau.oninput = (e) => {
      const value = Math.pow(10, parseFloat(e.target.value));
      $("tau-label").textContent = `τ = ${value.toExponential(2)}`;
      drawHistogram($("histogram"), m.histogram, value);
      clearTimeout(tauTimer);
      tauTimer = setTimeout(() => this.setTau(value), 150);
    };
    $("tau-label").textContent = `τ = ${m.tau.toExponential(2)}`;
    $("finetune").onclick = async () => {
      const iterations = 300;  // FinetuneRequest's default
      if (!window.confirm(`Start a new training run: this run's model, decomposed at τ = ${this.meta.tau.toExponential(2)}, `
                          + `trained ${iterations} more iterations?`)) return;
      const run = await api(`/api/runs/${this.runId}/finetune`, { method: "POST", body: { tau: this.meta.tau } });
      $("finetune-status").innerHTML = `training <a href="#/">${esc(run.name)}</a> (runs page)`;
    };
    drawHistogram($("histogram"), m.histogram, m.tau);
    this.updateCounts();
    $("mode").onchange = (e) => {
      if (e.target.value === "fly" && this.mode === "orbit") this.viewmat = this.orbit.viewmat();
      this.mode = e.target.value;
    };
    $("follow-input").onchange = () => this.updateInputFrame(true);
    $("to-input").onclick = () => this.jumpToInputCamera();
    this.initMouse();
    this.initEditing();
    this.initExports();
    this.initViewSettings();
  }

  setTau(value) {
    return new Promise((resolve) => {
      this.waiters.push({ kind: "decomposition", resolve });
      this.ws.send(JSON.stringify({ type: "tau", tau: value }));
    });
  }

  // The title, the set counts and the LoD menu all show what is kept now: after a delete or a
  // restore (the server's "decomposition" message) they change together.
  updateCounts() {
    const s = this.meta.decomposition;
    $("run-title").textContent = `${this.meta.name} · ${s.kept.toLocaleString()} Gaussians`;
    $("run-title").dataset.kept = s.kept;
    $("counts").textContent = `static ${s.static_kept.toLocaleString()} · dynamic ${s.dynamic_kept.toLocaleString()}`;
    $("counts").dataset.dynamic = s.dynamic_kept;
    $("counts").dataset.static = s.static_kept;
    const option = document.querySelector(`#lod option[value="${Number(s.lod)}"]`);
    if (option) option.textContent = `LoD ${Number(s.lod)} (${s.kept.toLocaleString()})`;
    this.updateHistory(s.history);
  }

  nearestInput() {
    const frames = this.meta.frames.filter((f) => f.split === "train");
    let best = null;
    for (const f of frames) if (!best || Math.abs(f.time - this.t) < Math.abs(best.time - this.t)) best = f;
    return best;
  }

  updateInputFrame(force = false) {
    const f = this.nearestInput();
    if (!f || (f === this.shownInput && !force)) return;
    this.shownInput = f;
    $("input-frame").src = withToken(`/api/runs/${this.runId}/frames/${f.index}/image`);
    $("input-label").textContent = `input frame ${f.id} (t = ${f.time.toFixed(3)})`;
    if ($("follow-input").checked) this.jumpToInputCamera();
  }

  jumpToInputCamera() {
    const f = this.nearestInput();
    if (!f) return;
    this.mode = "fly";
    $("mode").value = "fly";
    this.setViewmat(f.viewmat.flat());
  }

  status(text) {
    $("status").textContent = text;
  }

  // ------------------------------------------------------------------ hooks for tests and scripts

  setCamera(viewmat, K, width, height) {
    this.fixedSize = [width, height];
    this.canvas.width = width;
    this.canvas.height = height;
    this.fixedK = K;
    this.mode = "fly";
    this.fixedView = true;
    this.setViewmat(viewmat);
  }

  readPixels() {
    const gl = this.renderer.gl;
    const w = this.canvas.width, h = this.canvas.height;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const out = new Array(w * h * 3);
    for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
      const s = ((h - 1 - y) * w + x) * 4, d = (y * w + x) * 3;
      out[d] = px[s]; out[d + 1] = px[s + 1]; out[d + 2] = px[s + 2];
    }
    return { width: w, height: h, rgb: out };
  }
}

Object.assign(Viewer.prototype, navigation, timeline, editing, exportPanel, viewSettings, localView);
