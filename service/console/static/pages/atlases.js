// Atlases: frames, submaps, robots, active model version, calibration, last activity; admins
// create them.
import { get, post } from "../api.js";
import { errorBox, fmt, h, table } from "../ui.js";

export default async function render(container, { caller }) {
  const atlases = await get("/atlases");
  const robots = await Promise.all(atlases.map((a) => get(`/atlases/${encodeURIComponent(a.name)}/robots`)));
  const rows = atlases.map((a, i) => {
    const last = robots[i].map((r) => r.last_frame_at).sort().pop();
    return { ...a, robots: robots[i], last, __testid: `atlas-row-${a.name}` };
  });
  container.append(h("h1", {}, "Atlases"));
  if (caller.may("admin")) container.append(createForm());
  container.append(rows.length ? table([
    ["Atlas", (a) => h("a", { href: `#/atlas/${encodeURIComponent(a.name)}` }, a.name)],
    ["Frames", (a) => a.frames],
    ["Submaps", (a) => a.submaps],
    ["Robots", (a) => a.robots.map((r) => r.robot_id).join(", ") || "–"],
    ["Model", (a) => h("span", {}, `v${a.active_model_version} `,
      h("span", { class: `badge ${a.classifier_trained ? "ok" : ""}` }, a.classifier_trained ? "trained" : "untrained"))],
    ["Calibration", (a) => calibration(a.calibration)],
    ["Last activity", (a) => fmt.time(a.last || a.created_at)],
    ["Description", (a) => a.description],
  ], rows, (a) => { location.hash = `#/atlas/${encodeURIComponent(a.name)}`; })
    : h("p", { class: "muted" }, "No atlases yet."));
}

// "calibrated (v2, 200 frames)" or "uncalibrated": the summary's calibration state
function calibration(state) {
  if (!state || state.state !== "calibrated") {
    return h("span", { class: "badge", "data-testid": "calibration" }, "uncalibrated");
  }
  return h("span", { class: "badge ok", "data-testid": "calibration" },
    `calibrated (v${state.version}, ${state.frames_at_fit} frames)`);
}

function createForm() {
  const error = h("span", { class: "error" });
  const form = h("form", { class: "card", "data-testid": "create-atlas", onsubmit: async (e) => {
    e.preventDefault();
    const data = new FormData(form);
    try {
      await post("/atlases", { name: data.get("name"), description: data.get("description") });
      window.dispatchEvent(new HashChangeEvent("hashchange"));
    } catch (err) { error.replaceChildren(errorBox(err)); }
  } },
  h("label", {}, "New atlas", h("input", { name: "name", required: true, pattern: "[A-Za-z0-9][A-Za-z0-9._-]{0,63}" })),
  h("label", {}, "Description", h("input", { name: "description" })),
  h("button", { type: "submit" }, "Create atlas"), error);
  return form;
}
