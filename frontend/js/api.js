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

// POSTs a File as the raw request body, reporting the fraction sent to `onProgress` (fetch
// cannot report upload progress). Returns { done: Promise<JSON>, abort() }.
export function upload(path, file, onProgress) {
  const xhr = new XMLHttpRequest();
  const done = new Promise((resolve, reject) => {
    xhr.open("POST", path);
    if (token) xhr.setRequestHeader("Authorization", `Bearer ${token}`);
    xhr.setRequestHeader("Content-Type", file.type || "application/octet-stream");
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch (e) { /* not JSON */ }
      if (xhr.status < 300) return resolve(body);
      const detail = body && body.detail !== undefined ? body.detail : xhr.statusText;
      reject(new Error(`POST ${path}: ${xhr.status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`));
    };
    xhr.onerror = () => reject(new Error(`POST ${path}: the connection failed`));
    xhr.onabort = () => reject(new Error("upload cancelled"));
    xhr.send(file);
  });
  return { done, abort: () => xhr.abort() };
}
