// Keys (admins): create one (its token is shown this once), list, revoke.
import { del, get, post } from "../api.js";
import { errorBox, fmt, h, table } from "../ui.js";

export default async function render(container) {
  const listBox = h("div", { "data-testid": "keys" });
  const created = h("div");
  const error = h("div");
  const refresh = async () => {
    const keys = await get("/keys");
    listBox.replaceChildren(table([
      ["#", (k) => k.id],
      ["Name", (k) => k.name],
      ["Role", (k) => h("span", { class: "badge" }, k.role)],
      ["Atlases", (k) => (k.atlases.length ? k.atlases.join(", ") : "all")],
      ["Prefix", (k) => h("code", {}, `${k.prefix}…`)],
      ["Created", (k) => fmt.time(k.created_at)],
      ["State", (k) => (k.revoked_at ? h("span", { class: "badge bad", "data-testid": "key-state" }, `revoked ${fmt.time(k.revoked_at)}`) : h("span", { class: "badge ok", "data-testid": "key-state" }, "active"))],
      ["", (k) => (k.revoked_at ? "" : h("button", { class: "danger", "data-testid": "revoke-key", onclick: async () => {
        if (!confirm(`Revoke key ${k.id} (${k.name})? Whoever holds it loses access at once.`)) return;
        try { await del(`/keys/${k.id}`); } catch (err) { error.replaceChildren(errorBox(err)); }
        refresh();
      } }, "Revoke"))],
    ], keys.map((k) => ({ ...k, __testid: `key-${k.name}` }))));
  };
  const form = h("form", { class: "card", "data-testid": "create-key", onsubmit: async (e) => {
    e.preventDefault();
    const data = new FormData(form);
    const atlases = String(data.get("atlases") || "").split(",").map((x) => x.trim()).filter(Boolean);
    try {
      const key = await post("/keys", { name: data.get("name"), role: data.get("role"), atlases });
      created.replaceChildren(h("div", { class: "card" },
        h("strong", {}, `Key ${key.id} (${key.name}, ${key.role}) created. Copy it now: it is not shown again.`),
        h("p", { class: "token", "data-testid": "new-token" }, key.token)));
      form.reset(); error.replaceChildren();
      refresh();
    } catch (err) { error.replaceChildren(errorBox(err)); }
  } },
  h("label", {}, "Name", h("input", { name: "name", required: true, placeholder: "husky-1" })),
  h("label", {}, "Role", h("select", { name: "role" }, ["robot", "operator", "admin"].map((r) => h("option", { value: r }, r)))),
  h("label", {}, "Atlases (comma-separated, empty: all)", h("input", { name: "atlases" })),
  h("button", { type: "submit" }, "Create key"));
  container.append(h("h1", {}, "API keys"), form, created, error, listBox);
  await refresh();
}
