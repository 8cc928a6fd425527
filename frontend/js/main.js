// Entry point: `#/run/<id>` opens the viewer, anything else the runs page. A .ply or .splat
// file dropped anywhere (or chosen with "open a file") is shown in the viewer (local-view.js).

import { Viewer } from "./viewer.js";
import { makeDemoScene, showRuns, uploadVideos } from "./train.js";
import { $ } from "./dom.js";

async function route() {
  const m = location.hash.match(/^#\/run\/([0-9a-f]+)/);
  document.body.dataset.page = m ? "viewer" : "runs";
  if (m) {
    try {
      const viewer = new Viewer(m[1]);
      window.kgs = viewer;  // for scripts and tests: kgs.setTime(t), kgs.drawn(), kgs.readPixels()...
      await viewer.start();
      document.body.dataset.ready = "1";
    } catch (e) {
      $("loading").hidden = true;
      $("status").textContent = e.message;
      // Nothing to act on: every control of the panel goes inert (a bad id, a run without a model).
      document.querySelectorAll("#controls fieldset").forEach((f) => (f.disabled = true));
      document.body.dataset.failed = "1";
      throw e;
    }
  } else {
    $("demo").onclick = makeDemoScene;
    $("video-go").onclick = uploadVideos;
    await showRuns();
    document.body.dataset.ready = "1";
  }
}

async function openLocalFile(file) {
  try {
    const viewer = window.kgs || new Viewer(null);
    window.kgs = viewer;
    document.body.dataset.ready = "0";
    await viewer.openLocal(file.name, await file.arrayBuffer());
    document.body.dataset.ready = "1";
  } catch (e) {
    $("status").textContent = e.message;
    document.body.dataset.ready = "1";
  }
}

window.addEventListener("dragover", (e) => e.preventDefault());
window.addEventListener("drop", (e) => {
  e.preventDefault();
  const file = e.dataTransfer && e.dataTransfer.files[0];
  if (file) openLocalFile(file);
});
$("open-file").onchange = (e) => e.target.files[0] && openLocalFile(e.target.files[0]);
window.addEventListener("hashchange", () => location.reload());
route();
