// Text that reaches the DOM through an HTML template: every value a user or the server can
// set (run, scene and file names, statuses, ids) goes through `esc`, so that a name like
// `<img src=x onerror=…>` shows as text instead of running script.

const ENTITIES = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;", "`": "&#96;" };

export function esc(value) {
  return String(value ?? "").replace(/[&<>"'`]/g, (c) => ENTITIES[c]);
}

// The page's element with this id.
export const $ = (id) => document.getElementById(id);

// An ingest's finished stages as one short line: repeats of a stage ("register", "register, pass
// 2", …) merged into one entry with their count and summed seconds.
export function stageSummary(stages) {
  const merged = [];
  for (const [name, seconds] of stages || []) {
    const base = String(name).split(",")[0];
    const last = merged[merged.length - 1];
    if (last && last.base === base) {
      last.seconds += Number(seconds);
      last.count += 1;
    } else {
      merged.push({ base, seconds: Number(seconds), count: 1 });
    }
  }
  return merged.map((m) => `${m.base}${m.count > 1 ? ` ×${m.count}` : ""} ${m.seconds.toFixed(0)} s`).join(" · ");
}

// A duration for people: "42 s", "3 min 05 s", "1 h 02 min".
export function formatSeconds(seconds) {
  const s = Math.round(Number(seconds) || 0);
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${String(s % 60).padStart(2, "0")} s`;
  return `${Math.floor(s / 3600)} h ${String(Math.floor((s % 3600) / 60)).padStart(2, "0")} min`;
}
