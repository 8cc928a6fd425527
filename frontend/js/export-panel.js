// The viewer's export panel: starts an export job for the run at the viewer's LoD, exposure
// and (for .glb) time, polls it, and offers the download. Mixed into `Viewer`.

import { api, withToken } from "./api.js";
import { $, esc } from "./dom.js";

export const exportPanel = {
  initExports() {
    $("export-go").onclick = async () => {
      const format = $("export-format").value;
      const body = { format, lod: this.lod, exposure: this.exposure };
      if (format === "glb") body.times = String(this.t.toFixed(4));
      const job = await api(`/api/runs/${this.runId}/exports`, { method: "POST", body });
      $("export-status").textContent = `${format}: running…`;
      this.pollExport(job.id, format);
    };
  },

  async pollExport(id, format) {
    const job = await api(`/api/exports/${id}`);
    if (job.status === "queued" || job.status === "running") {
      $("export-status").textContent = job.queue_position ? `${format}: queued (${job.queue_position} in line)…` : `${format}: running…`;
      return setTimeout(() => this.pollExport(id, format), 700);
    }
    const el = $("export-status");
    if (job.status === "done") {
      el.innerHTML = `<a id="export-link" href="${esc(withToken(`/api/exports/${encodeURIComponent(id)}/download`))}">download ${esc(format)}</a>`;
    } else {
      el.textContent = `${format}: ${job.status} ${job.error || ""}`;
    }
  },
};
