// How the viewer draws and what it shares: field of view, background colour, view-dependent
// colour (SH), a screenshot, and the view and time kept in the page's URL so that a view can
// be shared or reloaded (`#/run/<id>?t=…&orbit=…` or `&fly=…`, `&fov=…`). Mixed into `Viewer`.

import { OrbitCamera } from "./camera.js";
import { $ } from "./dom.js";

const round = (v, k = 4) => Number(v.toFixed(k));

// The state a URL carries: {t, orbit: [tx, ty, tz, distance, yaw, pitch] | fly: [12] | null, fov}.
export function parseViewState(hash) {
  const q = new URLSearchParams((hash.split("?")[1] || ""));
  const nums = (key, n) => {
    const v = (q.get(key) || "").split(",").map(Number);
    return v.length === n && v.every(Number.isFinite) ? v : null;
  };
  const t = Number(q.get("t"));
  const fov = Number(q.get("fov"));
  return { t: q.has("t") && Number.isFinite(t) ? Math.min(1, Math.max(0, t)) : null,
           orbit: nums("orbit", 6), fly: nums("fly", 12), fov: fov >= 10 && fov <= 150 ? fov : null };
}

export function viewStateQuery({ t, orbit, fly, fov }) {
  const q = new URLSearchParams();
  q.set("t", round(t, 6));
  if (orbit) q.set("orbit", orbit.map((v) => round(v, 5)).join(","));
  if (fly) q.set("fly", fly.map((v) => round(v, 5)).join(","));
  if (fov) q.set("fov", round(fov, 2));
  return q.toString().replace(/%2C/g, ",");
}

export const viewSettings = {
  initViewSettings() {
    const m = this.meta;
    const f = this.fovFrame;
    this.trainingFov = f ? 2 * Math.atan(f.width / (2 * f.K[0][0])) * 180 / Math.PI : 60;
    const fov = $("fov");
    fov.value = String(Math.round(this.trainingFov));
    const label = () => { $("fov-label").textContent = `${Math.round(this.fovDeg || this.trainingFov)}°`; };
    fov.oninput = () => { this.fovDeg = parseFloat(fov.value); label(); this.dirty = true; this.saveViewState(); };
    label();
    this.background = [0, 0, 0];
    $("background").oninput = (e) => {
      const hex = e.target.value;
      this.background = [1, 3, 5].map((k) => parseInt(hex.slice(k, k + 2), 16) / 255);
      this.canvas.style.background = hex;
      this.dirty = true;
    };
    const sh = $("view-sh");
    this.viewDependent = m.sh_degree > 0;
    sh.checked = this.viewDependent;
    sh.disabled = !(m.sh_degree > 0);
    sh.parentElement.title = m.sh_degree > 0
      ? `Colour that changes with the viewing direction (the run's spherical harmonics, degree ${m.sh_degree}); off: each splat's base colour`
      : "This run's colours do not depend on the viewing direction (SH degree 0)";
    sh.onchange = () => { this.viewDependent = sh.checked; this.dirty = true; };
    $("screenshot").onclick = () => this.screenshot();
  },

  // The canvas as a PNG download named after the run and the frame.
  screenshot() {
    const k = this.nearestFrame() + 1;
    const name = `${(this.meta.name || this.runId).replace(/[^\w.-]+/g, "_")}-frame${k}.png`;
    this.dirty = true;
    return new Promise((resolve) => requestAnimationFrame(() => this.canvas.toBlob((blob) => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = name;
      a.click();
      setTimeout(() => URL.revokeObjectURL(a.href), 1000);
      resolve(name);
    }, "image/png")));
  },

  // ---------------------------------------------------------------- the URL

  viewState() {
    const s = { t: this.t, fov: this.fovDeg || null };
    if (this.mode === "orbit") {
      const o = this.orbit;
      s.orbit = [...o.target, o.distance, o.yaw, o.pitch];
    } else {
      s.fly = this.viewmat.slice(0, 12);
    }
    return s;
  },

  // Kept in the URL without a history entry per move (at most every 300 ms).
  saveViewState() {
    if (!this.urlReady) return;
    clearTimeout(this.urlTimer);
    this.urlTimer = setTimeout(() => {
      const base = location.hash.split("?")[0];
      history.replaceState(null, "", `${base}?${viewStateQuery(this.viewState())}`);
    }, 300);
  },

  // The view and time the page was opened with (a shared link, a reload).
  restoreViewState() {
    const s = parseViewState(location.hash);
    if (s.fov) { this.fovDeg = s.fov; $("fov").value = String(Math.round(s.fov)); $("fov-label").textContent = `${Math.round(s.fov)}°`; }
    if (s.orbit) {
      const [tx, ty, tz, distance, yaw, pitch] = s.orbit;
      this.orbit = new OrbitCamera([tx, ty, tz], Math.max(1e-3, distance), yaw, pitch, this.up);
      this.mode = "orbit";
      this.pivotSet = true;
    } else if (s.fly) {
      this.viewmat = [...s.fly, 0, 0, 0, 1];
      this.mode = "fly";
      $("mode").value = "fly";
      this.pivotSet = true;
    }
    if (s.t !== null) {  // onto a frame's own time when the link rounded it
      const times = this.frameTimes();
      const near = times.find((ft) => Math.abs(ft - s.t) < 1e-5);
      this.setTime(near !== undefined ? near : s.t);
    } else {
      this.setTime(this.t);  // the label names the first frame from the start
    }
    this.urlReady = true;
  },
};
