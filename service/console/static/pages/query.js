// Query: upload or drop an image and see the answer as the API gives it: the top-k frames with
// similarity and verification inliers, the decision's status, its loop_probability and why.
import { get, post } from "../api.js";
import { atlasPicker, errorBox, fmt, h, thumbImg } from "../ui.js";

export default async function render(container) {
  const picker = await atlasPicker(get, () => {});
  container.append(h("h1", {}, "Query"));
  if (!picker.current) { container.append(picker.element, h("p", { class: "muted" }, "No atlases yet.")); return; }
  const result = h("div", { "data-testid": "query-result" });
  const preview = h("img", { alt: "", style: "max-width:240px;display:none;border-radius:4px" });
  const file = h("input", { type: "file", accept: "image/jpeg,image/png,image/webp", "data-testid": "query-file" });
  const k = h("input", { type: "number", name: "k", value: 5, min: 1, max: 100, style: "min-width:80px" });
  const robot = h("input", { name: "robot_id", placeholder: "optional" });
  const run = async (blob, name) => {
    preview.src = URL.createObjectURL(blob); preview.style.display = "block";
    result.replaceChildren(h("p", { class: "muted" }, "Asking…"));
    const form = new FormData();
    form.append("image", blob, name);
    form.append("k", k.value);
    if (robot.value.trim()) form.append("robot_id", robot.value.trim());
    const atlas = container.querySelector("[data-testid=atlas-picker]").value;
    try { showAnswer(result, atlas, await post(`/atlases/${encodeURIComponent(atlas)}/query`, form)); }
    catch (err) { result.replaceChildren(errorBox(err)); }
  };
  file.addEventListener("change", () => { if (file.files[0]) run(file.files[0], file.files[0].name); });
  const drop = h("div", { class: "drop", "data-testid": "drop-zone" }, "Drop an image here, or ", file);
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault(); drop.classList.remove("over");
    const f = e.dataTransfer.files[0]; if (f) run(f, f.name);
  });
  container.append(h("div", { class: "card" }, picker.element, h("label", {}, "k", k), h("label", {}, "Asking robot", robot),
    h("div", { class: "row" }, h("div", { class: "grow" }, drop), preview)), result);
}

export function why(answer) {
  const m = answer.match;
  if (!m) return "The atlas has no frame the query may match.";
  const v = answer.verification;
  const d = answer.decision;
  const parts = [];
  if (v.enabled && d && d.loop_probability !== null) {
    parts.push(`loop_probability ${fmt.num(d.loop_probability)} (a loop needs ${d.threshold})`);
  }
  if (v.enabled) {
    parts.push(m.verified ? `verified: ${m.inliers} inliers ≥ ${v.min_inliers}` : `not verified: ${m.inliers ?? 0} inliers < ${v.min_inliers}`);
  } else {
    parts.push(`geometric verification off: similarity ${fmt.num(m.similarity)} against threshold ${fmt.num(answer.threshold, 2)}`);
  }
  if (d && d.failed) parts.push(`held back by ${d.failed}`);
  if (d && d.reason) parts.push(d.reason);
  if (answer.stay_frames > 0) parts.push(`the robot's current stay (${answer.stay_frames} frames) left out`);
  if (answer.margin !== null) parts.push(`margin over the best other submap ${fmt.num(answer.margin)}`);
  return parts.join("; ");
}

const STATUS_TEXT = { loop: "loop closure", candidate: "candidate (not a loop yet)", new_place: "new place" };

function showAnswer(result, atlas, answer) {
  const status = answer.status;
  const predicted = answer.predicted_submap.available
    ? `classifier: submap ${answer.predicted_submap.submap} (p = ${fmt.num(answer.predicted_submap.probability, 2)})`
    : answer.predicted_submap.reason;
  result.replaceChildren(
    h("div", { class: "card" },
      h("h2", {}, "Decision: ", h("span", { class: `badge ${status === "loop" ? "ok" : "bad"}`, "data-testid": "decision" }, STATUS_TEXT[status] ?? status)),
      h("p", { "data-testid": "why" }, why(answer)),
      answer.match ? h("p", {}, "Best match: frame ", h("strong", { "data-testid": "best-frame" }, answer.match.frame_id),
        ` in submap `, h("strong", { "data-testid": "best-submap" }, answer.match.submap), ` (robot ${answer.match.robot_id})`) : null,
      h("p", { class: "muted" }, predicted),
      h("p", { class: "muted" }, `model v${answer.model_version} · ${answer.keypoints} keypoints · ` +
        Object.entries(answer.timings_ms).map(([k, v]) => `${k} ${Math.round(v)} ms`).join(", "))),
    h("div", { class: "candidates" }, answer.candidates.map((c, i) => h("div", { class: `candidate ${i === 0 ? "best" : ""}`, "data-testid": "candidate" },
      thumbImg(atlas, c.frame_id),
      h("div", {}, h("strong", {}, `#${i + 1} frame ${c.frame_id}`), ` · ${c.submap} · ${c.robot_id}`),
      h("div", {}, `similarity ${fmt.num(c.similarity)}`),
      h("div", {}, c.inliers === null ? "not verified" : `${c.inliers} inliers (${fmt.num(c.inlier_ratio, 2)})` +
        (c.scale == null ? " " : ` · zoom ${fmt.num(c.scale, 2)} `),
        c.verified ? h("span", { class: "badge ok" }, "verified") : null)))));
}
