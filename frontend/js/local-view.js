// A splat file from the user's disk (dropped on the page, or chosen with "open a file"): a
// `.ply` or `.splat` drawn as one static set, with no server behind it. The viewer's drawing
// controls work (navigation, field of view, background, view-dependent colour, screenshot);
// those that need a run (time, decomposition, edits, exports, the input frames) are disabled.
// Mixed into `Viewer`.

import { SplatRenderer } from "./renderer.js";
import { parseSplatOrPly } from "./splat-files.js";
import { $ } from "./dom.js";

const SH_DEGREE = { 3: 1, 8: 2, 15: 3 };

export const localView = {
  async openLocal(name, buffer) {
    const set = parseSplatOrPly(name, buffer);  // before anything changes: a bad file leaves the page as it was
    if (this.ws) {  // a run was open: this page shows the file instead
      this.ws.onclose = null;
      this.ws.close();
      this.ws = null;
    }
    document.body.dataset.page = "viewer";
    this.local = true;
    this.runId = null;
    this.meta = { name: name.replace(/\.[^.]+$/, ""), frames: [], levels: [], sh_degree: set.sh ? SH_DEGREE[set.sh.bases] : 0,
                  frame_rate: null, exposure: 0, blur: null };
    if (!this.renderer) this.renderer = await SplatRenderer.create(this.canvas);
    this.initCamera();
    if (!this.mouseReady) { this.initMouse(); this.mouseReady = true; }
    this.initViewSettings();
    $("reset-view").onclick = () => this.resetView();
    $("frame-scene").onclick = () => this.frameScene();
    $("mode").onchange = (e) => {
      if (e.target.value === "fly" && this.mode === "orbit") this.viewmat = this.orbit.viewmat();
      this.mode = e.target.value;
    };
    for (const fs of document.querySelectorAll("#controls fieldset")) fs.disabled = fs !== $("mode").closest("fieldset");
    for (const id of ["exposure", "lod", "to-input", "follow-input"]) $(id).disabled = true;
    $("run-title").textContent = `${name} · ${set.count.toLocaleString()} Gaussians (a local file)`;
    $("status").textContent = "";
    this.loading(null);
    this.selected = new Set();
    this.static = set;
    this.dynamic = null;
    if (set.sh) this.renderer.uploadSH(set.sh);
    this.rebuild();
    this.resize();
    this.frameScene();
    if (!this.looping) {
      this.looping = true;
      window.addEventListener("resize", () => this.resize());
      requestAnimationFrame((now) => this.loop(now));
    }
    return set.count;
  },
};
