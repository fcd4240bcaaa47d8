// Jobs (operators): retraining jobs with live progress (polled), cancel; model versions with
// their metrics, activate one to roll forward or back.
import { get, post } from "../api.js";
import { atlasPicker, errorBox, fmt, h, table } from "../ui.js";

const POLL_MS = 1000;
const ACTIVE = new Set(["queued", "running"]);

export default async function render(container) {
  const picker = await atlasPicker(get, () => window.dispatchEvent(new HashChangeEvent("hashchange")));
  container.append(h("h1", {}, "Jobs & model versions"), picker.element);
  if (!picker.current) { container.append(h("p", { class: "muted" }, "No atlases yet.")); return; }
  const enc = encodeURIComponent(picker.current);
  const error = h("div");
  const jobsBox = h("div", { "data-testid": "jobs" });
  const modelsBox = h("div", { "data-testid": "models" });
  let timer = null, stopped = false;

  const refresh = async () => {
    try {
      const [jobs, models] = await Promise.all([get(`/atlases/${enc}/jobs`), get(`/atlases/${enc}/models`)]);
      jobsBox.replaceChildren(jobTable(jobs));
      modelsBox.replaceChildren(modelTable(models));
      error.replaceChildren();
      if (!stopped) timer = setTimeout(refresh, jobs.some((j) => ACTIVE.has(j.status)) ? POLL_MS : 5 * POLL_MS);
    } catch (err) { error.replaceChildren(errorBox(err)); if (!stopped) timer = setTimeout(refresh, 5 * POLL_MS); }
  };
  const act = (fn) => async () => { try { await fn(); } catch (err) { error.replaceChildren(errorBox(err)); } clearTimeout(timer); refresh(); };

  function jobTable(jobs) {
    if (!jobs.length) return h("p", { class: "muted" }, "No jobs yet.");
    return table([
      ["#", (j) => j.id],
      ["Kind", (j) => j.kind],
      ["Status", (j) => h("span", { class: `badge ${j.status === "succeeded" ? "ok" : j.status === "failed" ? "bad" : ACTIVE.has(j.status) ? "warn" : ""}`, "data-testid": "job-status" }, j.status)],
      ["Progress", (j) => h("div", {}, h("div", { class: "progress" }, h("div", { style: `width:${j.progress}%` })),
        h("span", { class: "muted", "data-testid": "job-progress" }, `${Math.round(j.progress)}%`))],
      ["Message", (j) => h("span", { "data-testid": "job-message" }, j.message || "")],
      ["Version", (j) => (j.model_version ? `v${j.model_version}` : "–")],
      ["Created", (j) => fmt.time(j.created_at)],
      ["", (j) => (ACTIVE.has(j.status) ? h("button", { class: "danger", "data-testid": "cancel-job", onclick: act(() => post(`/atlases/${enc}/jobs/${j.id}/cancel`)) }, "Cancel") : "")],
    ], jobs.map((j) => ({ ...j, __testid: `job-${j.id}` })));
  }

  function modelTable(models) {
    return table([
      ["Version", (m) => `v${m.version}`],
      ["State", (m) => (m.is_active ? h("span", { class: "badge ok", "data-testid": "active-version" }, "active") : "")],
      ["Trained", (m) => (m.trained ? "yes" : "no (initial heads)")],
      ["Metrics", (m) => metrics(m.metrics)],
      ["Created", (m) => fmt.time(m.created_at)],
      ["", (m) => (m.is_active ? "" : h("button", { class: "secondary", "data-testid": `activate-v${m.version}`, onclick: act(() => post(`/atlases/${enc}/models/${m.version}/activate`)) },
        m.version < Math.max(...models.filter((x) => x.is_active).map((x) => x.version)) ? "Roll back to this" : "Activate"))],
    ], models.map((m) => ({ ...m, __testid: `model-v${m.version}` })));
  }

  const shots = h("input", { type: "number", name: "shots", value: 2, min: 1, max: 100, style: "min-width:80px" });
  const epochs = h("input", { type: "number", name: "epochs", value: 40, min: 1, style: "min-width:80px" });
  const embed = h("input", { type: "number", name: "embed_dim", value: 32, min: 2, style: "min-width:80px" });
  const start = h("form", { class: "card", "data-testid": "start-job", onsubmit: (e) => {
    e.preventDefault();
    act(() => post(`/atlases/${enc}/jobs`, { kind: "retrain", params: { shots: +shots.value, epochs: +epochs.value, embed_dim: +embed.value } }))();
  } }, h("label", {}, "Shots per submap", shots), h("label", {}, "Epochs", epochs), h("label", {}, "Embedding size", embed),
  h("button", { type: "submit" }, "Start retraining"));

  container.append(start, error, h("h2", {}, "Jobs"), jobsBox, h("h2", {}, "Model versions"), modelsBox);
  await refresh();
  return () => { stopped = true; clearTimeout(timer); };
}

function metrics(m) {
  const entries = Object.entries(m || {}).filter(([, v]) => typeof v === "number");
  if (!entries.length) return h("span", { class: "muted" }, "–");
  return h("span", { class: "muted" }, entries.slice(0, 6).map(([k, v]) => `${k} ${Number.isInteger(v) ? v : v.toFixed(3)}`).join(" · "));
}
