// The runs page: scenes (make the demo scene, upload and ingest a video with its stages shown),
// start a run with a preset, live loss/PSNR chart, cancel, resume, open.

import { api, openStream, upload, withToken } from "./api.js";
import { drawChart } from "./chart.js";
import { $, esc, formatSeconds, stageSummary } from "./dom.js";

const ACTIVE = ["queued", "running", "cancelling"];
const RETRYABLE = ["uploaded", "failed", "cancelled", "interrupted"];

// One line for an ingest's progress: the stage, its count, the seconds so far, and the stages
// already done with their seconds (backend/worker.py: stage_writer).
function ingestProgress(p) {
  if (!p) return "starting…";
  const count = p.total ? ` ${p.done}/${p.total}` : "";
  const past = stageSummary(p.stages);
  return `${p.stage}${count} · ${Number(p.elapsed).toFixed(0)} s${past ? ` <span class="muted">(${esc(past)})</span>` : ""}`;
}

// A job's status, with its place in the server's queue while it waits for a core.
export function statusText(row) {
  return row.status === "queued" && row.queue_position ? `queued (${row.queue_position} in line)` : row.status;
}

function sceneItem(s) {
  const id = esc(s.id);
  const head = `<b>${esc(s.name)}</b> <span class="status">${esc(statusText(s))}</span>`;
  if (ACTIVE.includes(s.status)) {
    const line = s.status === "queued" ? "waiting for a free core…"
      : s.source === "ingest" ? ingestProgress(s.progress) : "synthesizing (about two minutes)…";
    return `<li data-scene="${id}">${head} <span class="ingest-progress">${line}</span>
      ${s.status !== "cancelling" ? `<button data-scene-cancel="${id}">cancel</button>` : ""}</li>`;
  }
  const error = s.error ? `<div class="error">${esc(s.error)}</div>` : "";
  const retry = s.source === "ingest" && RETRYABLE.includes(s.status) && s.videos
    ? `<button data-ingest="${id}" title="Ingest the uploaded video again with the options above">ingest again</button>` : "";
  const train = s.status === "done" ? `<button data-train="${id}">Train</button>` : "";
  const took = s.status === "done" && s.progress ? ` <span class="muted">ingested in ${Number(s.progress.elapsed).toFixed(0)} s</span>` : "";
  return `<li data-scene="${id}">${head}${took} ${train} ${retry}
    <button data-scene-delete="${id}" title="Delete the scene (refused while runs use it)">delete</button>${error}</li>`;
}

function ingestOptions() {
  return { max_size: parseInt($("video-size").value, 10), fixed_camera: $("video-fixed").checked };
}

let polling = null;

export async function showRuns() {
  const [scenes, runs] = await Promise.all([api("/api/scenes"), api("/api/runs")]);
  $("scene-list").innerHTML = scenes.length ? scenes.map(sceneItem).join("") : `<li class="muted">no scenes yet</li>`;
  // Keep the list current while a scene is being made.
  clearTimeout(polling);
  if ([...scenes, ...runs].some((s) => ACTIVE.includes(s.status))) polling = setTimeout(showRuns, 1000);
  const act = (sel, fn) => document.querySelectorAll(sel).forEach((b) => (b.onclick = () => fn(b).catch(report)));
  act("[data-scene-cancel]", (b) => api(`/api/scenes/${b.dataset.sceneCancel}/cancel`, { method: "POST" }).then(showRuns));
  act("[data-scene-delete]", (b) => api(`/api/scenes/${b.dataset.sceneDelete}`, { method: "DELETE" }).then(showRuns));
  act("[data-ingest]", (b) => api(`/api/scenes/${b.dataset.ingest}/ingest`, { method: "POST", body: ingestOptions() })
    .then(showRuns));
  $("run-list").innerHTML = runs.length
    ? runs.map((r) => `<li data-run="${esc(r.id)}">${r.has_model && r.status === "done"
          ? `<a href="#/run/${encodeURIComponent(r.id)}"><img class="thumb" loading="lazy" alt="${esc(r.name)} at mid-clip" src="${esc(withToken(`/api/runs/${encodeURIComponent(r.id)}/thumbnail`))}"></a>` : ""}
        <b>${esc(r.name)}</b> <span class="status">${esc(statusText(r))}</span>
        <span class="muted run-where">scene ${esc(r.scene_name || "?")} · started ${esc(new Date(r.created * 1000).toLocaleString())} · folder ${esc(r.folder)}</span>
        ${r.final_psnr_heldout ? ` · <span title="PSNR on the held-out views at the end of training">held-out ${esc(Number(r.final_psnr_heldout).toFixed(2))} dB</span>` : ""}
        ${r.gaussians ? ` · <span title="Gaussians in the final model">${esc(Number(r.gaussians).toLocaleString())} Gaussians</span>` : ""}
        ${r.train_seconds ? ` · <span title="Training time">${esc(formatSeconds(r.train_seconds))} training</span>` : ""}
        ${r.has_model ? `<a href="#/run/${encodeURIComponent(r.id)}">open</a>` : ""}
        ${["queued", "running"].includes(r.status) ? `<button data-watch="${esc(r.id)}">watch</button> <button data-cancel="${esc(r.id)}">cancel</button>` : ""}
        ${r.resumable ? `<button data-resume="${esc(r.id)}" title="${esc(r.error || "")}">resume</button>` : ""}</li>`).join("")
    : `<li class="muted">no runs yet: make the demo scene, then train it</li>`;
  document.querySelectorAll("[data-train]").forEach((b) => (b.onclick = async () => {
    const run = await api("/api/runs", { method: "POST", body: { scene_id: b.dataset.train, preset: $("train-preset").value,
      iterations: parseInt($("train-iterations").value, 10) || null,
      time_budget: parseFloat($("train-budget").value) * 60 || null, device: $("train-device").value } });
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

function report(e) {
  $("ingest-status").textContent = e.message;
}

// A scene name from a file name, within what the server accepts (letters, digits, . _ - space).
function sceneName(file) {
  return file.name.replace(/\.[^.]*$/, "").replace(/[^\w.\- ]/g, "_").slice(0, 80) || "video";
}

// Upload the video (held, so that a second camera's video can follow), then that one, then
// start the ingest; the scene list shows its stages from there.
export async function uploadVideos() {
  const file = $("video-file").files[0];
  const sharp = $("sharp-file").files[0];
  if (!file) { $("ingest-status").textContent = "choose a video first"; return; }
  const name = $("video-name").value.trim() || sceneName(file);
  const status = $("ingest-status");
  const send = async (path, f) => {
    const job = upload(path, f, (x) => { $("upload-pct").textContent = `${(100 * x).toFixed(0)}%`; });
    status.innerHTML = `uploading ${esc(f.name)} <span id="upload-pct">0%</span> <button id="upload-cancel">cancel</button>`;
    $("upload-cancel").onclick = job.abort;
    return job.done;
  };
  try {
    const scene = await send(`/api/scenes/upload?kind=video&hold=true&name=${encodeURIComponent(name)}`, file);
    try {
      if (sharp) await send(`/api/scenes/${scene.id}/video?role=sharp`, sharp);
      await api(`/api/scenes/${scene.id}/ingest`, { method: "POST", body: ingestOptions() });
    } catch (e) {
      await api(`/api/scenes/${scene.id}`, { method: "DELETE" }).catch(() => {});  // nothing half-made stays
      throw e;
    }
    status.textContent = "";
  } catch (e) {
    status.textContent = e.message;
  }
  await showRuns();
}

export async function makeDemoScene() {
  await api("/api/scenes", { method: "POST", body: { source: "synth", name: "sheet" } });
  await showRuns();
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
