// Revisit pairs (operators): what an adapt job learns from. Verified closures observe recorded
// and pairs operators labelled, both frames side by side; label a new pair by its two frame
// ids, delete a wrong one, and queue an adapt job over the pairs shown.
import { del, get, post } from "../api.js";
import { atlasPicker, errorBox, fmt, h, table, thumbImg } from "../ui.js";

const LIMIT = 200; // pairs listed, newest first

export default async function render(container) {
  const picker = await atlasPicker(get, () => window.dispatchEvent(new HashChangeEvent("hashchange")));
  container.append(h("h1", {}, "Revisit pairs"), picker.element);
  if (!picker.current) { container.append(h("p", { class: "muted" }, "No atlases yet.")); return; }
  const atlas = picker.current;
  const enc = encodeURIComponent(atlas);
  const listBox = h("div", { "data-testid": "pairs" });
  const summary = h("h2", {});
  const error = h("div", { "data-testid": "pairs-error" });
  const notice = h("div", { "data-testid": "pairs-notice" });
  const robot = h("input", { name: "robot", placeholder: "all robots", "data-testid": "pairs-robot" });

  const refresh = async () => {
    const query = robot.value.trim() ? `&robot=${encodeURIComponent(robot.value.trim())}` : "";
    const pairs = await get(`/atlases/${enc}/pairs?limit=${LIMIT}${query}`);
    summary.textContent = `${pairs.length}${pairs.length === LIMIT ? "+" : ""} pairs, newest first`;
    listBox.replaceChildren(pairs.length ? table([
      ["#", (p) => p.id],
      ["Frame", (p) => side(atlas, p.frame_id, p.robot_id, p.submap, "pair-frame")],
      ["Same place as", (p) => side(atlas, p.other_frame_id, p.other_robot_id, p.other_submap, "pair-other")],
      ["Source", (p) => h("span", { class: `badge ${p.source === "operator" ? "" : "ok"}`, "data-testid": "pair-source" }, p.source)],
      ["Inliers", (p) => p.inliers ?? "–"],
      ["Recorded", (p) => fmt.time(p.created_at)],
      ["", (p) => h("button", { class: "danger", "data-testid": "delete-pair", onclick: async () => {
        if (!confirm(`Delete pair ${p.id} (frames ${p.frame_id} and ${p.other_frame_id})? Adapt jobs will no longer learn from it.`)) return;
        try { await del(`/atlases/${enc}/pairs/${p.id}`); show(notice, `Pair ${p.id} deleted.`); error.replaceChildren(); }
        catch (err) { error.replaceChildren(errorBox(err)); notice.replaceChildren(); }
        await reload();
      } }, "Delete")],
    ], pairs.map((p) => ({ ...p, __testid: `pair-${p.id}` })))
      : h("p", { class: "muted" }, "No pairs yet: observe records one for each verified closure, or label one above."));
  };
  const reload = async () => { try { await refresh(); } catch (err) { error.replaceChildren(errorBox(err)); } };

  const form = h("form", { class: "card", "data-testid": "label-pair", onsubmit: async (e) => {
    e.preventDefault();
    const data = new FormData(form);
    try {
      const pair = await post(`/atlases/${enc}/pairs`, { frame_id: Number(data.get("frame_id")), other_frame_id: Number(data.get("other_frame_id")) });
      show(notice, `Pair ${pair.id} labelled: frames ${pair.frame_id} and ${pair.other_frame_id}.`);
      form.reset(); error.replaceChildren();
    } catch (err) { error.replaceChildren(errorBox(err)); notice.replaceChildren(); }
    await reload();
  } },
  h("strong", {}, "Label two frames as the same place"), h("br"),
  h("label", {}, "Frame id", h("input", { name: "frame_id", type: "number", min: 1, required: true })),
  h("label", {}, "Frame id of the same place", h("input", { name: "other_frame_id", type: "number", min: 1, required: true })),
  h("button", { type: "submit" }, "Label pair"));

  const queueAdapt = async () => {
    const robots = robot.value.trim() ? [robot.value.trim()] : [];
    try {
      const job = await post(`/atlases/${enc}/jobs`, { kind: "adapt", adaptation: { robots } });
      notice.replaceChildren(h("p", { class: "muted", "data-testid": "adapt-queued" }, `Adapt job ${job.id} queued (${job.status}). `,
        h("a", { href: "#/jobs" }, "Follow it on Jobs & models"), "."));
      error.replaceChildren();
    } catch (err) { error.replaceChildren(errorBox(err)); notice.replaceChildren(); }
  };
  const adapt = h("form", { class: "card", "data-testid": "pairs-filter", onsubmit: (e) => { e.preventDefault(); reload(); } },
    h("label", {}, "Robot (filters the list and the job)", robot),
    h("button", { type: "submit", class: "secondary" }, "Filter"), " ",
    h("button", { type: "button", "data-testid": "adapt-button", onclick: queueAdapt }, "Adapt with these pairs"),
    h("p", { class: "muted" }, "An adapt job learns a whitening from the pairs and is activated only when it is not worse on held-out pairs; a job with too few pairs is refused with its reason."));

  container.append(h("div", { class: "row" }, h("div", { class: "grow" }, form), h("div", { class: "grow" }, adapt)),
    error, notice, summary, listBox);
  await refresh();
}

function side(atlas, frameId, robotId, submap, testid) {
  return h("figure", { class: "pair-side", "data-testid": testid },
    thumbImg(atlas, frameId), h("figcaption", {}, `frame ${frameId} · ${robotId} · ${submap}`));
}

function show(box, text) { box.replaceChildren(h("p", { class: "muted" }, text)); }
