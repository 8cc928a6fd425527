// Text that reaches the DOM through an HTML template: every value a user or the server can
// set (run, scene and file names, statuses, ids) goes through `esc`, so that a name like
// `<img src=x onerror=…>` shows as text instead of running script.

const ENTITIES = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;", "`": "&#96;" };

export function esc(value) {
  return String(value ?? "").replace(/[&<>"'`]/g, (c) => ENTITIES[c]);
}

// The page's element with this id.
export const $ = (id) => document.getElementById(id);
