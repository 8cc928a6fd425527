// The viewer page: streams a run's splats from the server, draws them with WebGL2, and wires
// the controls (time, sets, overlays, tau, exposure, LoD, camera, editing, exports).

import { api, openStream, withToken } from "./api.js";
import { parseBuffer } from "./buffers.js";
import { FLAG_DYNAMIC, packSet, textureRows, TEX_WIDTH, SPLATS_PER_ROW } from "./pack.js";
import { SplatRenderer } from "./renderer.js";
import { ORBIT_RADIANS_PER_PIXEL, OrbitCamera, cameraCenter, flyMove, flyTurn, focusDepth, intrinsics, orbitAtDepth,
  project } from "./camera.js";
import { drawHistogram } from "./chart.js";
import { esc } from "./dom.js";
import { frontOf } from "./pick.js";
import { arrowScale, arrowSegments } from "./arrows.js";

const $ = (id) => document.getElementById(id);

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
    this.connect();
    this.resize();
    window.addEventListener("resize", () => this.resize());
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
    const f = this.fovFrame;
    if (f) {  // the training camera's field of view, fitted to the canvas
      const fovx = 2 * Math.atan(f.width / (2 * f.K[0][0])) * 180 / Math.PI;
      return intrinsics(w, h, fovx);
    }
    return intrinsics(w, h, 60);
  }

  resize() {
    if (this.fixedSize) return;
    const r = this.canvas.getBoundingClientRect();
    this.canvas.width = Math.max(16, Math.round(r.width));
    this.canvas.height = Math.max(16, Math.round(r.height));
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
    this.ws.send(JSON.stringify({ type: "subscribe", lod: this.lod, velocity: true }));
    this.requestTime();
  }

  requestTime() {
    if (!this.ws || this.ws.readyState !== 1) return;
    this.seq += 1;
    this.ws.send(JSON.stringify({ type: "time", t: this.t, exposure: this.exposure, seq: this.seq }));
  }

  onJSON(msg) {
    if (msg.type === "split") {
      this.meta.split = msg;
      this.meta.tau = msg.tau;
      this.updateCounts();
      const waiting = this.waiters.filter((w) => w.kind === "split");
      waiting.forEach((w) => w.resolve(msg));
      this.waiters = this.waiters.filter((w) => w.kind !== "split");
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
    if (set.header.kind === "static") {
      this.static = set;
      this.pivotOnContent(set);
    } else {
      if (set.header.version !== (this.static && this.static.header.version)) {
        // arrived before the matching static set: keep it, it will be drawn with it
      }
      this.dynamic = set;
      this.lastDynamicT = set.header.t;
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
    if (this.playing) {
      const dt = this.lastNow ? (now - this.lastNow) / 1000 : 0;
      const duration = Math.max(1, this.meta.frames.length) / 30;  // play at 30 frames per second
      this.setTime((this.t + (dt * this.speed) / duration) % 1);
    }
    this.lastNow = now;
    this.fly();
    if (this.dirty && this.sortPending === null) {
      const viewmat = this.currentViewmat();
      this.renderer.draw({ viewmat, K: this.intrinsics(), show: this.show, overlay: this.overlay,
                           stride: this.stride, arrows: this.arrows });
      this.dirty = false;
      this.frameCount += 1;
      this.resolveWaiters();
      this.updateInputFrame();
    }
    requestAnimationFrame((n) => this.loop(n));
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
      const t = this.t;
      this.waiters.push({ kind: "frame", resolve,
        ready: () => this.static && this.dynamic && Math.abs(this.lastDynamicT - t) < 1e-9 && this.sortPending === null });
      this.dirty = true;
    });
  }

  setTime(t, fromSlider = false) {
    this.t = Math.min(1, Math.max(0, t));
    if (!fromSlider) $("time").value = Math.round(this.t * 1000);
    $("time-label").textContent = `t = ${this.t.toFixed(3)}`;
    this.requestTime();
  }

  // ------------------------------------------------------------------ controls

  initControls() {
    const m = this.meta;
    $("time").oninput = (e) => this.setTime(e.target.value / 1000, true);
    $("play").onclick = () => { this.playing = !this.playing; $("play").textContent = this.playing ? "Pause" : "Play"; };
    $("speed").onchange = (e) => (this.speed = parseFloat(e.target.value));
    $("step-back").onclick = () => this.setTime(this.t - m.dt);
    $("step-fwd").onclick = () => this.setTime(this.t + m.dt);
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
    // Say which exposure "as captured" renders with; with none recorded it would change nothing.
    const captured = document.querySelector('#exposure option[value="captured"]');
    captured.textContent = `as captured (exposure ${Number(m.exposure || 0).toFixed(2)})`;
    captured.disabled = !(m.exposure > 0);
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
  }

  setTau(value) {
    return new Promise((resolve) => {
      this.waiters.push({ kind: "split", resolve });
      this.ws.send(JSON.stringify({ type: "tau", tau: value }));
    });
  }

  // The title, the set counts and the LoD menu all show what is kept now: after a delete or a
  // restore (the server's "split" message) they change together.
  updateCounts() {
    const s = this.meta.split;
    $("run-title").textContent = `${this.meta.name} · ${s.kept.toLocaleString()} Gaussians`;
    $("run-title").dataset.kept = s.kept;
    $("counts").textContent = `static ${s.static_kept.toLocaleString()} · dynamic ${s.dynamic_kept.toLocaleString()}`;
    $("counts").dataset.dynamic = s.dynamic_kept;
    $("counts").dataset.static = s.static_kept;
    const option = document.querySelector(`#lod option[value="${Number(s.lod)}"]`);
    if (option) option.textContent = `LoD ${Number(s.lod)} (${s.kept.toLocaleString()})`;
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

  initMouse() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("pointerdown", (e) => {
      if (this.tool !== "none") return this.editPointer(e, "down");
      drag = { x: e.clientX, y: e.clientY, button: e.button };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (this.tool !== "none") return this.editPointer(e, "move");
      if (!drag) return;
      const dx = (e.clientX - drag.x) / c.clientWidth, dy = (e.clientY - drag.y) / c.clientHeight;
      drag.x = e.clientX; drag.y = e.clientY;
      this.pivotSet = true;  // the user's view from here on
      if (this.mode === "orbit") {
        const turn = ORBIT_RADIANS_PER_PIXEL;
        if (drag.button === 2 || e.shiftKey) this.orbit.pan(dx, dy);
        else this.orbit.rotate(-turn * dx * c.clientWidth, turn * dy * c.clientHeight);
      } else {
        this.viewmat = flyTurn(this.viewmat, 2 * dx, -2 * dy);
      }
      this.dirty = true;
      this.requestSort();
    });
    c.addEventListener("pointerup", (e) => {
      if (this.tool !== "none") return this.editPointer(e, "up");
      drag = null;
    });
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.pivotSet = true;
      if (this.mode === "orbit") this.orbit.zoom(Math.exp(e.deltaY * 0.001));
      else this.viewmat = flyMove(this.viewmat, -e.deltaY * 0.002, 0, 0);
      this.dirty = true;
      this.requestSort();
    }, { passive: false });
    this.keys = new Set();
    window.addEventListener("keydown", (e) => { if (e.target.tagName !== "INPUT") this.keys.add(e.code); });
    window.addEventListener("keyup", (e) => this.keys.delete(e.code));
  }

  fly() {
    if (this.mode !== "fly" || !this.keys || !this.keys.size) return;
    const s = 0.02;
    const k = this.keys;
    const f = (k.has("KeyW") ? s : 0) - (k.has("KeyS") ? s : 0);
    const r = (k.has("KeyD") ? s : 0) - (k.has("KeyA") ? s : 0);
    const u = (k.has("KeyE") ? s : 0) - (k.has("KeyQ") ? s : 0);
    if (f || r || u) {
      this.viewmat = flyMove(this.viewmat, f, r, u);
      this.dirty = true;
      this.requestSort();
    }
  }

  // ------------------------------------------------------------------ editing

  initEditing() {
    this.tool = "none";
    $("tool").onchange = (e) => { this.tool = e.target.value; this.canvas.style.cursor = this.tool === "none" ? "" : "crosshair"; };
    $("sel-clear").onclick = () => this.setSelection(new Set());
    for (const op of ["hide", "delete"]) $(`edit-${op}`).onclick = () => this.edit(op, [...this.selected]);
    $("edit-unhide").onclick = () => this.edit("unhide", []);
    $("edit-restore").onclick = () => this.edit("restore", []);
    $("edit-crop").onclick = () => this.cropToSelection();
  }

  // Indices (within the LoD level) of drawn splats whose centre projects inside `inside(u, v)`.
  // The splats whose centres fall inside a screen region. By default only those at the front:
  // a box around a ball must not take the wall behind it (deleting would leave a hole there).
  // "Through" (#select-through) takes everything inside, at every depth.
  pick(inside) {
    const vm = this.currentViewmat(), K = this.intrinsics();
    const hits = [];  // [index, u, v, depth]
    for (const set of [this.static, this.dynamic]) {
      if (!set) continue;
      const isDyn = set === this.dynamic;
      if ((isDyn && !(this.show & 2)) || (!isDyn && !(this.show & 1))) continue;
      for (let i = 0; i < set.count; i++) {
        const [u, v, z] = project(vm, K, [set.positions[3 * i], set.positions[3 * i + 1], set.positions[3 * i + 2]]);
        if (z > 0.01 && inside(u, v)) hits.push([set.index[i], u, v, z]);
      }
    }
    if ($("select-through").checked) return new Set(hits.map((h) => h[0]));
    return new Set(frontOf(hits).map((h) => h[0]));
  }

  editPointer(e, phase) {
    const r = this.canvas.getBoundingClientRect();
    const sx = this.canvas.width / r.width, sy = this.canvas.height / r.height;
    const u = (e.clientX - r.left) * sx, v = (e.clientY - r.top) * sy;
    const box = $("select-box");
    if (this.tool === "box") {
      if (phase === "down") { this.boxStart = [u, v]; box.style.display = "block"; }
      if (!this.boxStart) return;
      const [u0, v0] = this.boxStart;
      Object.assign(box.style, { left: `${Math.min(u0, u) / sx}px`, top: `${Math.min(v0, v) / sy}px`,
                                 width: `${Math.abs(u - u0) / sx}px`, height: `${Math.abs(v - v0) / sy}px` });
      if (phase === "up") {
        box.style.display = "none";
        this.selectBox(u0, v0, u, v, e.shiftKey);
        this.boxStart = null;
      }
    } else if (this.tool === "brush") {
      if (phase === "down") this.brushing = true;
      if (phase === "up") this.brushing = false;
      if (!this.brushing) return;
      const rad = parseFloat($("brush-size").value) * sx;
      const picked = this.pick((a, b) => (a - u) ** 2 + (b - v) ** 2 <= rad * rad);
      this.setSelection(new Set([...this.selected, ...picked]));
    }
  }

  selectBox(u0, v0, u1, v1, add = false) {
    const [a0, a1] = [Math.min(u0, u1), Math.max(u0, u1)], [b0, b1] = [Math.min(v0, v1), Math.max(v0, v1)];
    const picked = this.pick((u, v) => u >= a0 && u <= a1 && v >= b0 && v <= b1);
    this.setSelection(add ? new Set([...this.selected, ...picked]) : picked);
    return picked.size;
  }

  setSelection(sel) {
    this.selected = sel;
    $("sel-count").textContent = `${sel.size.toLocaleString()} selected`;
    this.packedStatic = null;  // repack the flags
    this.rebuild();
  }

  async edit(op, indices, crop) {
    const res = await api(`/api/runs/${this.runId}/edits`, { method: "POST", body: { op, lod: this.lod, indices, crop } });
    if (op === "delete" || op === "hide") this.selected = new Set();
    $("sel-count").textContent = `${this.selected.size} selected`;
    return res;
  }

  cropToSelection() {
    if (!this.selected.size) return this.status("select the region to keep first");
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const set of [this.static, this.dynamic]) {
      if (!set) continue;
      for (let i = 0; i < set.count; i++) {
        if (!this.selected.has(set.index[i])) continue;
        for (let k = 0; k < 3; k++) {
          lo[k] = Math.min(lo[k], set.positions[3 * i + k]);
          hi[k] = Math.max(hi[k], set.positions[3 * i + k]);
        }
      }
    }
    return this.edit("crop", [], { min: lo, max: hi });
  }

  // ------------------------------------------------------------------ exports

  initExports() {
    $("export-go").onclick = async () => {
      const format = $("export-format").value;
      const body = { format, lod: this.lod, exposure: this.exposure };
      if (format === "glb") body.times = String(this.t.toFixed(4));
      const job = await api(`/api/runs/${this.runId}/exports`, { method: "POST", body });
      $("export-status").textContent = `${format}: running…`;
      this.pollExport(job.id, format);
    };
  }

  async pollExport(id, format) {
    const job = await api(`/api/exports/${id}`);
    if (job.status === "queued" || job.status === "running") return setTimeout(() => this.pollExport(id, format), 700);
    const el = $("export-status");
    if (job.status === "done") {
      el.innerHTML = `<a id="export-link" href="${esc(withToken(`/api/exports/${encodeURIComponent(id)}/download`))}">download ${esc(format)}</a>`;
    } else {
      el.textContent = `${format}: ${job.status} ${job.error || ""}`;
    }
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

