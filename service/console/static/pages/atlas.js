// One atlas: submaps, each robot's trajectory as a strip of thumbnails in time order, and a
// frame's details (pose, intrinsics, keypoints drawn on demand).
import { get, post } from "../api.js";
import { errorBox, fmt, h, s, table, thumbImg } from "../ui.js";

const STRIP = 200; // frames per robot strip

export default async function render(container, { args }) {
  const name = args[0];
  if (!name) { location.hash = "#/atlases"; return; }
  const enc = encodeURIComponent(name);
  const [atlas, submaps, robots] = await Promise.all([
    get(`/atlases/${enc}`), get(`/atlases/${enc}/submaps`), get(`/atlases/${enc}/robots`),
  ]);
  const detail = h("div", { class: "card", "data-testid": "frame-detail" }, h("p", { class: "muted" }, "Select a frame."));
  container.append(
    h("h1", {}, `Atlas ${atlas.name}`),
    h("p", { class: "muted" }, `${atlas.frames} frames · ${atlas.submaps} submaps · model v${atlas.active_model_version} · ${atlas.description}`),
  );
  const strips = h("div", { class: "grow" }, h("h2", {}, "Trajectories"));
  for (const robot of robots) {
    const frames = await get(`/atlases/${enc}/frames?robot=${encodeURIComponent(robot.robot_id)}&limit=${STRIP}`);
    strips.append(h("div", { class: "card" },
      h("strong", {}, robot.robot_id), h("span", { class: "muted" }, ` · ${robot.frames} frames · last ${fmt.time(robot.last_frame_at)}`),
      h("div", { class: "strip", "data-testid": `strip-${robot.robot_id}` }, frames.map((f) => {
        const item = h("div", { class: "thumb", "data-testid": "thumb", title: `frame ${f.frame_id} · ${f.submap}`, onclick: () => {
          for (const el of container.querySelectorAll(".thumb.selected")) el.classList.remove("selected");
          item.classList.add("selected");
          showFrame(detail, name, f);
        } }, thumbImg(name, f.frame_id), h("span", { class: "caption" }, f.submap));
        return item;
      }))));
  }
  if (!robots.length) strips.append(h("p", { class: "muted" }, "No frames yet."));
  const side = h("div", { class: "grow" }, h("h2", {}, "Frame"), detail, h("h2", {}, "Submaps"),
    table([["Submap", (x) => x.name], ["Frames", (x) => x.frames], ["Created", (x) => fmt.time(x.created_at)]], submaps),
    addSubmap(enc));
  container.append(h("div", { class: "row" }, strips, side));
}

function addSubmap(enc) {
  const error = h("span", { class: "error" });
  const form = h("form", { onsubmit: async (e) => {
    e.preventDefault();
    try { await post(`/atlases/${enc}/submaps`, { name: new FormData(form).get("name") }); window.dispatchEvent(new HashChangeEvent("hashchange")); }
    catch (err) { error.replaceChildren(errorBox(err)); }
  } }, h("label", {}, "New submap", h("input", { name: "name", required: true })), h("button", { type: "submit", class: "secondary" }, "Add"), error);
  return form;
}

function showFrame(detail, atlas, f) {
  const img = thumbImg(atlas, f.frame_id);
  const big = h("div", { class: "big" }, img);
  const button = h("button", { class: "secondary", "data-testid": "show-keypoints", onclick: async () => {
    button.disabled = true;
    const kp = await get(`/atlases/${encodeURIComponent(atlas)}/frames/${f.frame_id}/keypoints?limit=300`);
    const svg = s("svg", { viewBox: `0 0 ${kp.width} ${kp.height}`, preserveAspectRatio: "none", "data-testid": "keypoints" });
    const r = Math.max(kp.width, kp.height) / 160;
    for (const [x, y] of kp.keypoints) svg.append(s("circle", { cx: x, cy: y, r, fill: "none", stroke: "#22ff88", "stroke-width": r / 2 }));
    big.append(svg);
    button.textContent = `${kp.keypoints.length} of ${kp.total} keypoints`;
  } }, "Show keypoints");
  const pose = f.pose ? `q ${fmt.list(f.pose.rotation)} · t ${fmt.list(f.pose.translation)}` : "–";
  const k = f.intrinsics ? `fx ${f.intrinsics.fx} fy ${f.intrinsics.fy} cx ${f.intrinsics.cx} cy ${f.intrinsics.cy}` : "–";
  detail.replaceChildren(big, h("p", {}, button), h("dl", {},
    h("dt", {}, "Frame"), h("dd", {}, f.frame_id),
    h("dt", {}, "Robot"), h("dd", {}, f.robot_id),
    h("dt", {}, "Submap"), h("dd", {}, f.submap),
    h("dt", {}, "Timestamp"), h("dd", {}, f.timestamp ?? "–"),
    h("dt", {}, "Pose"), h("dd", { "data-testid": "pose" }, pose),
    h("dt", {}, "Intrinsics"), h("dd", { "data-testid": "intrinsics" }, k),
    h("dt", {}, "Size"), h("dd", {}, `${f.width} × ${f.height} px, ${f.keypoints} keypoints`),
    h("dt", {}, "Added"), h("dd", {}, fmt.time(f.created_at))));
}
