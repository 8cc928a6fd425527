// The viewer's export panel: the chosen format's options (times, the video's camera path, size
// and side-by-side, framing for web viewers), an export job for the run at the viewer's LoD
// and exposure, its stages while it runs, and the download. Mixed into `Viewer`.

import { api, withToken } from "./api.js";
import { $, esc } from "./dom.js";

export const exportPanel = {
  initExports() {
    const panel = $("export-panel");
    const sync = () => {
      panel.dataset.format = $("export-format").value;
      panel.dataset.times = $("export-times").value;
    };
    $("export-format").onchange = () => {
      const format = $("export-format").value;
      // A .ply is interchange (other tools expect the run's coordinates); the web formats open framed.
      $("export-web").checked = format === "splat" || format === "splatv";
      // One .splat or .glb is a moment; a .splatv and a video play the clip.
      $("export-times").value = format === "splatv" || format === "mp4" ? "all" : "now";
      sync();
    };
    $("export-times").onchange = sync;
    $("export-path").onchange = () => {
      const training = $("export-path").value === "training";
      $("export-side").disabled = !training;
      if (!training) $("export-side").checked = false;
    };
    const n = this.frameTimes().length;
    $("export-from").max = $("export-to").max = String(n);
    $("export-to").value = String(n);
    $("export-format").onchange();
    $("export-go").onclick = () => this.startExport().catch((e) => { $("export-status").textContent = e.message; });
  },

  // The request body the panel's options describe (the server's ExportRequest).
  exportBody() {
    const format = $("export-format").value;
    const body = { format, lod: this.lod, exposure: this.exposure };
    const times = this.frameTimes();
    const mode = format === "glb" ? "now" : $("export-times").value;
    if (mode === "now") body.times = this.t.toFixed(4);
    if (mode === "range") {
      const a = Math.max(1, parseInt($("export-from").value, 10) || 1);
      const b = Math.min(times.length, parseInt($("export-to").value, 10) || times.length);
      if (b < a) throw new Error(`frames ${a} to ${b}: the last frame comes before the first`);
      body.times = times.slice(a - 1, b).map((t) => t.toFixed(6)).join(",");
    }
    if (format === "mp4") {
      body.camera_path = $("export-path").value;
      body.side_by_side = $("export-side").checked && body.camera_path === "training";
      if ($("export-size").value) body.size = parseInt($("export-size").value, 10);
      if (body.camera_path === "view") {
        const K = this.intrinsics(), w = this.canvas.width, h = this.canvas.height;
        const vm = this.currentViewmat();
        body.view = { viewmat: [0, 1, 2, 3].map((r) => vm.slice(4 * r, 4 * r + 4)),
                      fov_deg: 2 * Math.atan(w / (2 * K[0])) * 180 / Math.PI, width: w, height: h };
        if (mode === "all") delete body.times;
      }
    }
    if (["ply-seq", "splat", "splatv"].includes(format)) body.web_frame = $("export-web").checked;
    return body;
  },

  async startExport() {
    const body = this.exportBody();
    // The last export's link goes at once: until the request returns it would fetch the old file.
    $("export-status").textContent = `${body.format}: starting…`;
    const job = await api(`/api/runs/${this.runId}/exports`, { method: "POST", body });
    this.pollExport(job.id, body.format);
    return job;
  },

  async pollExport(id, format) {
    const job = await api(`/api/exports/${id}`);
    const el = $("export-status");
    if (job.status === "queued" || job.status === "running") {
      const p = job.progress;
      el.textContent = job.queue_position ? `${format}: queued (${job.queue_position} in line)…`
        : p ? `${format}: ${p.stage}${p.total ? ` ${p.done} of ${p.total}` : ""} · ${Math.round(p.elapsed)} s`
          : `${format}: starting…`;
      return setTimeout(() => this.pollExport(id, format), 500);
    }
    if (job.status === "done") {
      el.innerHTML = `<a id="export-link" href="${esc(withToken(`/api/exports/${encodeURIComponent(id)}/download`))}">download ${esc(format)}</a>`;
    } else {
      el.textContent = `${format}: ${job.status} ${job.error || ""}`;
    }
  },
};
