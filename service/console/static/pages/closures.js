// Loop closures between robots: a list, a graph (robots as nodes, closures as edges with
// counts), and one closure's two images side by side with the relative pose and, for a
// closure an observation found (both frames stored), the verified matches drawn between them.
import { frameThumb, get, thumbnailUrl } from "../api.js";
import { atlasPicker, errorBox, fmt, h, imgFrom, s, table, thumbImg } from "../ui.js";

export default async function render(container) {
  const picker = await atlasPicker(get, () => window.dispatchEvent(new HashChangeEvent("hashchange")));
  container.append(h("h1", {}, "Loop closures"), picker.element);
  if (!picker.current) { container.append(h("p", { class: "muted" }, "No atlases yet.")); return; }
  const atlas = picker.current;
  const closures = await get(`/atlases/${encodeURIComponent(atlas)}/loop-closures?limit=500`);
  const detail = h("div", { class: "card", "data-testid": "closure-detail" }, h("p", { class: "muted" }, "Select a closure."));
  container.append(h("div", { class: "row" },
    h("div", { class: "grow" }, h("h2", {}, "Robots and their closures"), graph(closures)),
    h("div", { class: "grow" }, h("h2", {}, "Closure"), detail)));
  container.append(h("h2", {}, `${closures.length} closures, newest first`), closures.length ? table([
    ["#", (c) => c.id],
    ["Robot", (c) => c.robot_id],
    ["Matched robot", (c) => c.matched_robot_id],
    ["Submap", (c) => c.submap],
    ["Similarity", (c) => fmt.num(c.similarity)],
    ["Source", (c) => c.source],
    ["Model", (c) => `v${c.model_version}`],
    ["Found", (c) => fmt.time(c.created_at)],
  ], closures.map((c) => ({ ...c, __testid: `closure-${c.id}` })), (c) => show(detail, atlas, c.id))
    : h("p", { class: "muted" }, "No closures between robots yet: they appear when a robot's query or observation recognises a place another robot mapped."));
}

function graph(closures) {
  const robots = [...new Set(closures.flatMap((c) => [c.robot_id, c.matched_robot_id]))].sort();
  const counts = new Map();
  for (const c of closures) {
    const key = [c.robot_id, c.matched_robot_id].sort().join("\u0000");
    counts.set(key, (counts.get(key) || 0) + 1);
  }
  const size = 320, r = 120, c0 = size / 2;
  const pos = new Map(robots.map((name, i) => {
    const a = (2 * Math.PI * i) / Math.max(robots.length, 1) - Math.PI / 2;
    return [name, [c0 + r * Math.cos(a), c0 + r * Math.sin(a)]];
  }));
  const svg = s("svg", { class: "graph", width: size, height: size, viewBox: `0 0 ${size} ${size}`, "data-testid": "closure-graph" });
  const max = Math.max(1, ...counts.values());
  for (const [key, n] of counts) {
    const [a, b] = key.split("\u0000");
    const [x1, y1] = pos.get(a), [x2, y2] = pos.get(b);
    svg.append(s("line", { x1, y1, x2, y2, stroke: "#2457c5", "stroke-width": 1 + (5 * n) / max, "stroke-opacity": 0.7 }));
    svg.append(s("text", { x: (x1 + x2) / 2 + 4, y: (y1 + y2) / 2 - 4, "data-testid": "edge-count" }, String(n)));
  }
  for (const [name, [x, y]] of pos) {
    svg.append(s("circle", { cx: x, cy: y, r: 18, fill: "#101828" }));
    svg.append(s("text", { x, y: y + 34, "text-anchor": "middle" }, name));
  }
  if (!robots.length) svg.append(s("text", { x: c0, y: c0, "text-anchor": "middle" }, "no closures"));
  return h("div", { class: "card" }, svg);
}

async function show(detail, atlas, id) {
  const enc = encodeURIComponent(atlas);
  const c = await get(`/atlases/${enc}/loop-closures/${id}`);
  const pose = c.relative_pose
    ? `R q ${fmt.list(c.relative_pose.rotation)} · t direction ${fmt.list(c.relative_pose.translation)}`
    : "not estimated (no intrinsics with the query)";
  const query = `${c.robot_id}'s ${c.source}` + (c.query_frame_id ? ` (frame ${c.query_frame_id})` : "");
  const matched = `${c.matched_robot_id}'s frame ${c.frame.frame_id} (${c.frame.submap})`;
  let images;
  if (c.query_frame_id) {
    try { images = await matchView(atlas, c.id, query, matched); } catch (err) { images = h("div", {}, pair(atlas, c, query, matched), errorBox(err)); }
  } else {
    images = h("div", {}, pair(atlas, c, query, matched),
      h("p", { class: "muted" }, "Matches are drawn for closures an observation found: a query keeps no frame to match again."));
  }
  detail.replaceChildren(
    images,
    h("dl", {},
      h("dt", {}, "Similarity"), h("dd", {}, fmt.num(c.similarity)),
      h("dt", {}, "Inliers"), h("dd", {}, c.inliers ?? "not verified"),
      h("dt", {}, "Relative pose"), h("dd", { "data-testid": "relative-pose" }, pose),
      h("dt", {}, "Model"), h("dd", {}, `v${c.model_version}`),
      h("dt", {}, "Found"), h("dd", {}, fmt.time(c.created_at))));
}

function pair(atlas, c, query, matched) {
  const enc = encodeURIComponent(atlas);
  return h("div", { class: "pair" },
    h("figure", {}, imgFrom(thumbnailUrl(`/atlases/${enc}/loop-closures/${c.id}/query-thumbnail`), { alt: "query", "data-testid": "closure-query" }),
      h("figcaption", {}, query)),
    h("figure", {}, thumbImg(atlas, c.frame.frame_id, { "data-testid": "closure-match" }),
      h("figcaption", {}, matched)));
}

// Both frames' thumbnails side by side in one SVG, at one height, and a line per inlier from
// the query frame's keypoint to the matched frame's: the stored pixel coordinates are scaled
// by each frame's decoded size to the drawn thumbnail (thumbnails keep the aspect ratio).
async function matchView(atlas, id, query, matched) {
  const m = await get(`/atlases/${encodeURIComponent(atlas)}/loop-closures/${id}/matches?limit=400`);
  const [queryUrl, frameUrl] = await Promise.all([frameThumb(atlas, m.query_frame.frame_id), frameThumb(atlas, m.frame.frame_id)]);
  const height = 192, gap = 12;
  const sq = height / m.query_frame.height, sf = height / m.frame.height;
  const wq = m.query_frame.width * sq, wf = m.frame.width * sf, x0 = wq + gap;
  const svg = s("svg", { class: "matches", viewBox: `0 0 ${wq + gap + wf} ${height + 18}`, "data-testid": "closure-matches" });
  for (const [href, x, width, testid] of [[queryUrl, 0, wq, "closure-query"], [frameUrl, x0, wf, "closure-match"]]) {
    const image = s("image", { href, x, y: 0, width, height, preserveAspectRatio: "none", "data-testid": testid });
    image.addEventListener("load", () => image.setAttribute("data-loaded", "true"));
    svg.append(image);
  }
  m.pairs.forEach(([xq, yq, xf, yf], i) => svg.append(s("line", {
    x1: xq * sq, y1: yq * sq, x2: x0 + xf * sf, y2: yf * sf,
    stroke: `hsl(${(i * 47) % 360} 90% 55%)`, "stroke-width": 1, "stroke-opacity": 0.85,
  })));
  svg.append(s("text", { x: 0, y: height + 14 }, query), s("text", { x: x0, y: height + 14 }, matched));
  const shown = m.pairs.length < m.inliers ? ` (${m.pairs.length} drawn)` : "";
  return h("div", {}, svg, h("p", { class: "muted", "data-testid": "match-summary" },
    `${m.inliers} inliers of ${m.matches} ${m.matcher} matches${shown}, ${m.model} model, recomputed from the stored keypoints`));
}
