// Moving the viewer's camera with the mouse and keyboard: orbit (drag to turn, right-drag or
// shift-drag to pan, wheel to zoom) or fly (drag to look, wheel and W/A/S/D/Q/E to move), and
// the viewer's shortcuts (docs/viewer.md). Mixed into `Viewer` (viewer.js); the editing tools
// take the pointer while one is active.

import { ORBIT_RADIANS_PER_PIXEL, OrbitCamera, flyMove, flyTurn } from "./camera.js";
import { $ } from "./dom.js";

// Fly speed in scene units per second (the same at any frame rate).
const FLY_SPEED = 1.2;

// Keys typed into a form control belong to it (a focused dropdown would also take W/A/S/D).
function typing(target) {
  return ["INPUT", "SELECT", "TEXTAREA", "BUTTON"].includes(target.tagName) || target.isContentEditable;
}

export const navigation = {
  initMouse() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("pointerdown", (e) => {
      // The canvas takes the keyboard back from whichever control had it.
      if (document.activeElement && document.activeElement !== document.body) document.activeElement.blur();
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
    window.addEventListener("keydown", (e) => {
      if (typing(e.target)) return;
      if ((e.ctrlKey || e.metaKey) && !e.altKey && (e.code === "KeyZ" || e.code === "KeyY")) {
        e.preventDefault();  // (the browser's own undo would act on no field here)
        const redo = e.code === "KeyY" || e.shiftKey;
        if (!$(redo ? "edit-redo" : "edit-undo").disabled) this.edit(redo ? "redo" : "undo", []);
        return;
      }
      if ((e.ctrlKey || e.metaKey) && !e.altKey && (e.code === "KeyA" || e.code === "KeyI")) {
        e.preventDefault();  // (not the page's text selection)
        if (e.code === "KeyA") this.selectAll(); else this.invertSelection();
        return;
      }
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      if (this.shortcut(e.code)) e.preventDefault();
      else this.keys.add(e.code);
    });
    window.addEventListener("keyup", (e) => this.keys.delete(e.code));
    window.addEventListener("blur", () => this.keys.clear());
  },

  // One-press shortcuts; true when `code` is one.
  shortcut(code) {
    const actions = {
      Space: () => this.togglePlay(),
      ArrowLeft: () => this.stepFrame(-1),
      ArrowRight: () => this.stepFrame(1),
      KeyF: () => this.frameScene(),
      KeyR: () => this.resetView(),
      Home: () => this.resetView(),
      Delete: () => this.selected && this.selected.size && this.edit("delete", [...this.selected]),
      Escape: () => this.setSelection(new Set()),
      KeyP: () => this.screenshot(),
    };
    if (!(code in actions)) return false;
    actions[code]();
    return true;
  },

  fly(dt) {
    if (this.mode !== "fly" || !this.keys || !this.keys.size) return;
    const s = FLY_SPEED * dt;
    const k = this.keys;
    const f = (k.has("KeyW") ? s : 0) - (k.has("KeyS") ? s : 0);
    const r = (k.has("KeyD") ? s : 0) - (k.has("KeyA") ? s : 0);
    const u = (k.has("KeyE") ? s : 0) - (k.has("KeyQ") ? s : 0);
    if (f || r || u) {
      this.viewmat = flyMove(this.viewmat, f, r, u);
      this.dirty = true;
      this.requestSort();
    }
  },

  // The opening view again: the first training camera, orbiting about what it sees.
  resetView() {
    this.fixedView = false;
    this.fixedK = null;
    this.fovDeg = null;
    $("fov").value = String(Math.round(this.trainingFov));
    $("fov-label").textContent = `${Math.round(this.trainingFov)}°`;
    this.initCamera();
    $("mode").value = "orbit";
    this.pivotOnContent(this.static && this.static.count ? this.static : this.dynamic);
    this.dirty = true;
    this.requestSort();
  },

  // Orbit about the middle of the selection, or of every shown splat, from far enough to see it
  // whole (its points within the 5th to 95th percentile of their distance from the middle).
  frameScene() {
    const points = [];
    for (const set of [this.static, this.dynamic]) {
      if (!set || !set.count) continue;
      for (let i = 0; i < set.count; i++) {
        if (this.selected && this.selected.size && !this.selected.has(set.index ? set.index[i] : i)) continue;
        points.push([set.positions[3 * i], set.positions[3 * i + 1], set.positions[3 * i + 2]]);
      }
    }
    if (!points.length) return;
    const median = (v) => { const s = [...v].sort((a, b) => a - b); return s[s.length >> 1]; };
    const centre = [0, 1, 2].map((k) => median(points.map((p) => p[k])));
    const dist = points.map((p) => Math.hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2])).sort((a, b) => a - b);
    const radius = Math.max(1e-3, dist[Math.floor(0.95 * (dist.length - 1))]);
    const K = this.intrinsics(), h = this.canvas.height;
    const halfFov = Math.atan(h / (2 * K[4]));
    this.fixedView = false;
    this.orbit = OrbitCamera.fromViewmat(this.currentViewmat(), centre, this.up);
    this.orbit.distance = 1.1 * radius / Math.sin(halfFov);
    this.mode = "orbit";
    $("mode").value = "orbit";
    this.pivotSet = true;
    this.dirty = true;
    this.requestSort();
  },
};
