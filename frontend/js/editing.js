// Selecting and editing splats in the viewer: box and brush selection of the splats in front
// (or through, at every depth), a moving object by a click, all and invert, each replacing,
// adding to or subtracting from the selection; then hide, delete, restore or crop through the
// server's edit layer (`/api/runs/{id}/edits`; the model itself is never changed), with undo
// and redo kept there too, so that they survive a reload. Mixed into `Viewer`.

import { api } from "./api.js";
import { project } from "./camera.js";
import { $ } from "./dom.js";
import { frontOf } from "./pick.js";

export const editing = {
  initEditing() {
    this.tool = "none";
    $("tool").onchange = (e) => { this.tool = e.target.value; this.canvas.style.cursor = this.tool === "none" ? "" : "crosshair"; };
    $("sel-clear").onclick = () => this.setSelection(new Set());
    $("sel-all").onclick = () => this.selectAll();
    $("sel-invert").onclick = () => this.invertSelection();
    for (const op of ["hide", "delete"]) $(`edit-${op}`).onclick = () => this.edit(op, [...this.selected]);
    $("edit-unhide").onclick = () => this.edit("unhide", []);
    $("edit-restore").onclick = () => this.edit("restore", []);
    $("edit-crop").onclick = () => this.cropToSelection();
    $("edit-undo").onclick = () => this.edit("undo", []);
    $("edit-redo").onclick = () => this.edit("redo", []);
  },

  // The undo and redo buttons say which step they revert (the server's edit history).
  updateHistory(h) {
    const undo = $("edit-undo"), redo = $("edit-redo");
    undo.disabled = !(h && h.undo);
    redo.disabled = !(h && h.redo);
    undo.title = h && h.undo ? `Undo "${h.undo}" (Ctrl+Z)` : "Nothing to undo (Ctrl+Z)";
    redo.title = h && h.redo ? `Redo "${h.redo}" (Ctrl+Shift+Z or Ctrl+Y)` : "Nothing to redo";
    $("edit-history").textContent = h && (h.undo_steps || h.redo_steps)
      ? `${h.undo_steps} step${h.undo_steps === 1 ? "" : "s"} back${h.undo ? `, last: ${h.undo}` : ""}`
        + (h.redo_steps ? ` · ${h.redo_steps} to redo` : "")
      : "";
  },

  // Indices (within the LoD level) of drawn splats whose centre projects inside `inside(u, v)`.
  // The splats whose centres fall inside a screen region. By default only those at the front:
  // a box around a ball must not take the wall behind it (deleting would leave a hole there).
  // "Through" (#select-through) takes everything inside, at every depth.
  // `hits`: the raw [index, u, v, depth] of the front splats, nearest first (the object tool).
  pick(inside, hits_ = false) {
    const vm = this.currentViewmat(), K = this.intrinsics();
    const hits = [], drawn = [];  // [index, u, v, depth]
    for (const set of [this.static, this.dynamic]) {
      if (!set) continue;
      const isDyn = set === this.dynamic;
      if ((isDyn && !(this.show & 2)) || (!isDyn && !(this.show & 1))) continue;
      for (let i = 0; i < set.count; i++) {
        const [u, v, z] = project(vm, K, [set.positions[3 * i], set.positions[3 * i + 1], set.positions[3 * i + 2]]);
        if (!(z > 0.01)) continue;
        const h = [set.index[i], u, v, z];
        drawn.push(h);
        if (inside(u, v)) hits.push(h);
      }
    }
    if (hits_) return frontOf(hits, drawn).sort((a, b) => a[3] - b[3]);
    if ($("select-through").checked) return new Set(hits.map((h) => h[0]));
    return new Set(frontOf(hits, drawn).map((h) => h[0]));
  },

  // The indices of every splat drawn now (the sets shown, at this LoD).
  shownIndices() {
    const out = new Set();
    for (const set of [this.static, this.dynamic]) {
      if (!set) continue;
      const isDyn = set === this.dynamic;
      if ((isDyn && !(this.show & 2)) || (!isDyn && !(this.show & 1))) continue;
      for (let i = 0; i < set.count; i++) out.add(set.index[i]);
    }
    return out;
  },

  selectAll() { this.setSelection(this.shownIndices()); },

  invertSelection() {
    this.setSelection(new Set([...this.shownIndices()].filter((i) => !this.selected.has(i))));
  },

  // How `picked` changes the selection: the mode menu, or Shift (add) and Alt (subtract).
  // The selection mode a pointer event asks for: Alt subtracts, Shift adds, else the menu's.
  selectionMode(e = null) {
    return e && e.altKey ? "subtract" : e && e.shiftKey ? "add" : $("sel-mode").value;
  },

  // `picked` combined with the selection by `mode` ("replace", "add" or "subtract").
  combine(picked, mode) {
    if (mode === "add") return new Set([...this.selected, ...picked]);
    if (mode === "subtract") return new Set([...this.selected].filter((i) => !picked.has(i)));
    return picked;
  },

  // Where a world point lands on the canvas, in canvas pixels: [u, v, depth].
  screenPoint(p) {
    return project(this.currentViewmat(), this.intrinsics(), p);
  },

  // The moving object under canvas pixel (u, v): the nearest visible splat within a few pixels,
  // then every dynamic Gaussian connected to it (the server's select-object).
  async selectObjectAt(u, v, mode = this.selectionMode()) {
    const r = 8;
    const hits = this.pick((a, b) => (a - u) ** 2 + (b - v) ** 2 <= r * r, true);
    const d = this.dynamic;
    const dynamicIds = new Set(d ? d.index : []);
    const seed = hits.find((h) => dynamicIds.has(h[0]));
    if (!seed) { this.status("no moving object under the cursor"); return 0; }
    const res = await api(`/api/runs/${this.runId}/select-object`, { method: "POST",
      body: { index: seed[0], t: this.t, lod: this.lod } });
    this.setSelection(this.combine(new Set(res.indices), mode));
    this.status(`object: ${res.indices.length.toLocaleString()} moving Gaussians`);
    return res.indices.length;
  },

  editPointer(e, phase) {
    const r = this.canvas.getBoundingClientRect();
    const sx = this.canvas.width / r.width, sy = this.canvas.height / r.height;
    const u = (e.clientX - r.left) * sx, v = (e.clientY - r.top) * sy;
    const box = $("select-box");
    if (this.tool === "object") {
      if (phase === "up") this.selectObjectAt(u, v, this.selectionMode(e));
      return;
    }
    if (this.tool === "box") {
      if (phase === "down") { this.boxStart = [u, v]; box.style.display = "block"; }
      if (!this.boxStart) return;
      const [u0, v0] = this.boxStart;
      Object.assign(box.style, { left: `${Math.min(u0, u) / sx}px`, top: `${Math.min(v0, v) / sy}px`,
                                 width: `${Math.abs(u - u0) / sx}px`, height: `${Math.abs(v - v0) / sy}px` });
      if (phase === "up") {
        box.style.display = "none";
        this.selectBox(u0, v0, u, v, this.selectionMode(e));
        this.boxStart = null;
      }
    } else if (this.tool === "brush") {
      if (phase === "down") {  // a stroke in "replace" starts a new selection, then grows it
        this.brushing = true;
        const mode = this.selectionMode(e);
        this.brushSubtract = mode === "subtract";
        if (mode === "replace") this.selected = new Set();
      }
      if (phase === "up") this.brushing = false;
      if (!this.brushing) return;
      const rad = parseFloat($("brush-size").value) * sx;
      const picked = this.pick((a, b) => (a - u) ** 2 + (b - v) ** 2 <= rad * rad);
      this.setSelection(this.brushSubtract ? new Set([...this.selected].filter((i) => !picked.has(i)))
        : new Set([...this.selected, ...picked]));
    }
  },

  // The Gaussians in a canvas box, combined with the selection by `mode`.
  selectBox(u0, v0, u1, v1, mode = this.selectionMode()) {
    const [a0, a1] = [Math.min(u0, u1), Math.max(u0, u1)], [b0, b1] = [Math.min(v0, v1), Math.max(v0, v1)];
    const picked = this.pick((u, v) => u >= a0 && u <= a1 && v >= b0 && v <= b1);
    this.setSelection(this.combine(picked, mode));
    return picked.size;
  },

  setSelection(sel) {
    this.selected = sel;
    $("sel-count").textContent = `${sel.size.toLocaleString()} selected`;
    this.packedStatic = null;  // repack the flags
    this.rebuild();
  },

  async edit(op, indices, crop) {
    const res = await api(`/api/runs/${this.runId}/edits`, { method: "POST", body: { op, lod: this.lod, indices, crop } });
    if (op === "delete" || op === "hide") this.selected = new Set();
    $("sel-count").textContent = `${this.selected.size} selected`;
    return res;
  },

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
  },
};
