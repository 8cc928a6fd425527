// Entry point: `#/run/<id>` opens the viewer, anything else the runs page.

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

window.addEventListener("hashchange", () => location.reload());
route();
