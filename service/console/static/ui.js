// Small DOM helpers: elements are built with textContent, never innerHTML, so API data cannot inject markup.
import { frameThumb } from "./api.js";

export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "class") el.className = v;
    else if (k === "style") el.style.cssText = v; // through the CSSOM: the CSP allows no style attributes
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const child of children.flat()) {
    if (child === undefined || child === null || child === false) continue;
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return el;
}

const SVG = "http://www.w3.org/2000/svg";
export function s(tag, attrs = {}, ...children) {
  const el = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  for (const child of children) el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  return el;
}

export function table(columns, rows, onClick) {
  return h("table", {},
    h("thead", {}, h("tr", {}, columns.map(([label]) => h("th", {}, label)))),
    h("tbody", {}, rows.map((row) => h("tr", {
      class: onClick ? "clickable" : undefined,
      onclick: onClick ? () => onClick(row) : undefined,
      "data-testid": row.__testid,
    }, columns.map(([, cell]) => h("td", {}, cell(row)))))));
}

export function thumbImg(atlas, frameId, attrs = {}) {
  const img = h("img", { alt: `frame ${frameId}`, "data-frame": frameId, ...attrs });
  frameThumb(atlas, frameId).then((url) => { img.src = url; }, () => { img.alt = "unavailable"; });
  return img;
}

export function imgFrom(promise, attrs = {}) {
  const img = h("img", attrs);
  promise.then((url) => { img.src = url; }, () => { img.alt = "unavailable"; });
  return img;
}

export const fmt = {
  num: (v, d = 3) => (v === null || v === undefined ? "–" : Number(v).toFixed(d)),
  time: (iso) => (iso ? new Date(iso).toLocaleString() : "–"),
  list: (v) => (v && v.length ? v.map((x) => Number(x).toFixed(3)).join(", ") : "–"),
};

export function errorBox(err) {
  return h("p", { class: "error", role: "alert" }, err && err.detail ? `${err.status}: ${err.detail}` : String(err));
}

// The atlas a page works on: one picker shared by the pages, remembered for the tab.
export async function atlasPicker(get, onChange) {
  const atlases = await get("/atlases");
  let current = sessionStorage.getItem("loopnet.atlas");
  if (!atlases.some((a) => a.name === current)) current = atlases.length ? atlases[0].name : null;
  const select = h("select", { "data-testid": "atlas-picker", onchange: (e) => {
    sessionStorage.setItem("loopnet.atlas", e.target.value); onChange(e.target.value);
  } }, atlases.map((a) => h("option", { value: a.name, selected: a.name === current }, a.name)));
  if (current) sessionStorage.setItem("loopnet.atlas", current);
  return { element: h("label", {}, "Atlas", select), current };
}
