// The runs page: scenes (make the demo scene), start a run, live loss/PSNR chart, cancel, resume, open.

import { api, openStream } from "./api.js";
import { drawChart } from "./chart.js";
import { esc } from "./dom.js";

const $ = (id) => document.getElementById(id);

export async function showRuns() {
  const [scenes, runs] = await Promise.all([api("/api/scenes"), api("/api/runs")]);
  $("scene-list").innerHTML = scenes.length
    ? scenes.map((s) => `<li>${esc(s.name)} <span class="muted">${esc(s.status)}</span>
        ${s.status === "done" ? `<button data-train="${esc(s.id)}">Train (fast)</button>` : ""}</li>`).join("")
    : `<li class="muted">no scenes yet</li>`;
  $("run-list").innerHTML = runs.length
    ? runs.map((r) => `<li data-run="${esc(r.id)}"><b>${esc(r.name)}</b> <span class="status">${esc(r.status)}</span>
        <span class="muted run-where">${esc(r.scene_name || "?")} · ${esc(new Date(r.created * 1000).toLocaleString())} · ${esc(r.folder)}</span>
        ${r.final_psnr_heldout ? ` · ${esc(Number(r.final_psnr_heldout).toFixed(2))} dB` : ""}
        ${r.has_model ? `<a href="#/run/${encodeURIComponent(r.id)}">open</a>` : ""}
        ${["queued", "running"].includes(r.status) ? `<button data-watch="${esc(r.id)}">watch</button> <button data-cancel="${esc(r.id)}">cancel</button>` : ""}
        ${r.resumable ? `<button data-resume="${esc(r.id)}" title="${esc(r.error || "")}">resume</button>` : ""}</li>`).join("")
    : `<li class="muted">no runs yet: make the demo scene, then train it</li>`;
  document.querySelectorAll("[data-train]").forEach((b) => (b.onclick = async () => {
    const run = await api("/api/runs", { method: "POST", body: { scene_id: b.dataset.train, preset: "fast",
      iterations: parseInt($("train-iterations").value, 10) || null } });
    await showRuns();
    watch(run.id);
  }));
  document.querySelectorAll("[data-cancel]").forEach((b) => (b.onclick = async () => {
    await api(`/api/runs/${b.dataset.cancel}/cancel`, { method: "POST" });
    setTimeout(showRuns, 1500);
  }));
  document.querySelectorAll("[data-resume]").forEach((b) => (b.onclick = async () => {
    await api(`/api/runs/${b.dataset.resume}/resume`, { method: "POST" });
    await showRuns();
    watch(b.dataset.resume);
  }));
    document.querySelectorAll("[data-watch]").forEach((b) => (b.onclick = () => watch(b.dataset.watch)));
}

export async function makeDemoScene() {
  await api("/api/scenes", { method: "POST", body: { source: "synth", name: "sheet" } });
  $("train-status").textContent = "synthesizing the demo scene (about two minutes)…";
  const poll = async () => {
    const scenes = await api("/api/scenes");
    await showRuns();
    if (scenes.some((s) => ["queued", "running"].includes(s.status))) setTimeout(poll, 2000);
    else $("train-status").textContent = "";
  };
  poll();
}

let watching = null;

export async function watch(runId) {
  if (watching) watching.close();
  const log = await api(`/api/runs/${runId}/log`);
  const loss = log.map((r) => [r.train_seconds, r.loss]);
  const psnr = log.map((r) => [r.train_seconds, r.psnr_heldout]);
  const draw = () => drawChart($("train-chart"), [
    { label: "loss", color: "#ff8c00", points: loss, digits: 4 },
    { label: "PSNR dB", color: "#6ab0ff", points: psnr, digits: 2 }], { xLabel: "seconds", title: `run ${runId}` });
  draw();
  const ws = openStream(runId);
  watching = ws;
  ws.onmessage = (e) => {
    if (typeof e.data !== "string") return;
    const msg = JSON.parse(e.data);
    if (msg.type === "progress") {
      loss.push([msg.elapsed, msg.loss]);
      if (msg.psnr_heldout !== null) psnr.push([msg.elapsed, msg.psnr_heldout]);
      $("train-status").textContent = `iteration ${msg.iteration}/${msg.iterations} · ${msg.gaussians.toLocaleString()} Gaussians · ${(100 * msg.dynamic_share).toFixed(0)}% dynamic`;
      draw();
    } else if (msg.type === "status") {
      $("train-status").textContent = `run ${msg.status}${msg.error ? ": " + msg.error : ""}`;
      showRuns();
    }
  };
}
