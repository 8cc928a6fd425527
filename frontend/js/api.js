// REST and WebSocket client. The access token (when the server requires one) comes from the
// page URL (?token=...) and is sent as a Bearer header, or as a query parameter on sockets.

const params = new URLSearchParams(location.search);
export const token = params.get("token");

export async function api(path, { method = "GET", body, raw = false } = {}) {
  const headers = {};
  if (token) headers["Authorization"] = `Bearer ${token}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) {
    let detail = r.statusText;
    try { detail = (await r.json()).detail; } catch (e) { /* not JSON */ }
    throw new Error(`${method} ${path}: ${r.status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
  }
  if (raw) return r;
  return r.status === 204 ? null : r.json();
}

export function withToken(url) {
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}

export function openStream(runId) {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(withToken(`${proto}://${location.host}/api/runs/${runId}/stream`));
  ws.binaryType = "arraybuffer";
  return ws;
}
