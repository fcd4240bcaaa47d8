// The API as the console uses it: same origin, the key from this tab's sessionStorage.
const KEY = "loopnet.key";

export class ApiError extends Error {
  constructor(status, detail) { super(`${status}: ${detail}`); this.status = status; this.detail = detail; }
}

export const session = {
  get key() { return sessionStorage.getItem(KEY) || ""; },
  set key(value) { value ? sessionStorage.setItem(KEY, value) : sessionStorage.removeItem(KEY); },
};

function headers(extra = {}) {
  const out = { ...extra };
  if (session.key) out.Authorization = `Bearer ${session.key}`;
  return out;
}

export async function api(method, path, body) {
  const init = { method, headers: headers() };
  if (body instanceof FormData) init.body = body;
  else if (body !== undefined) { init.body = JSON.stringify(body); init.headers["Content-Type"] = "application/json"; }
  const response = await fetch(`/v1${path}`, init);
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail ?? detail; } catch { /* not JSON */ }
    throw new ApiError(response.status, detail);
  }
  return response.status === 204 ? null : response.json();
}

export const get = (path) => api("GET", path);
export const post = (path, body) => api("POST", path, body);
export const del = (path) => api("DELETE", path);

// Thumbnails need the key, so <img src> cannot fetch them: fetch once, keep an object URL.
const thumbs = new Map();
export function thumbnailUrl(path) {
  if (!thumbs.has(path)) {
    thumbs.set(path, fetch(`/v1${path}`, { headers: headers() }).then(async (r) => {
      if (!r.ok) throw new ApiError(r.status, r.statusText);
      return URL.createObjectURL(await r.blob());
    }));
  }
  return thumbs.get(path);
}
export const frameThumb = (atlas, id) => thumbnailUrl(`/atlases/${encodeURIComponent(atlas)}/frames/${id}/thumbnail`);
export function forgetThumbnails() { thumbs.clear(); }
