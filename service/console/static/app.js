// The console's shell: sign-in with an API key, navigation by role, a page per hash route.
import { ApiError, forgetThumbnails, get, session } from "./api.js";
import { errorBox } from "./ui.js";
import atlases from "./pages/atlases.js";
import atlas from "./pages/atlas.js";
import closures from "./pages/closures.js";
import query from "./pages/query.js";
import jobs from "./pages/jobs.js";
import pairs from "./pages/pairs.js";
import keys from "./pages/keys.js";

const ROLES = { robot: 1, operator: 2, admin: 3 };
const PAGES = {
  atlases: { render: atlases, role: "robot" },
  atlas: { render: atlas, role: "robot" },
  closures: { render: closures, role: "robot" },
  query: { render: query, role: "robot" },
  jobs: { render: jobs, role: "operator" },
  pairs: { render: pairs, role: "operator" },
  keys: { render: keys, role: "admin" },
};

export const caller = { name: "", role: "robot", may(role) { return ROLES[this.role] >= ROLES[role]; } };
let stopPage = null; // a page's clean-up (polling timers)

const $ = (id) => document.getElementById(id);

async function signIn(key) {
  session.key = key;
  try {
    const me = await get("/whoami");
    Object.assign(caller, { name: me.name, role: me.role });
    return true;
  } catch (err) {
    session.key = "";
    if (err instanceof ApiError) $("login-error").textContent = `${err.status}: ${err.detail}`;
    else $("login-error").textContent = String(err);
    return false;
  }
}

function showLogin() {
  $("login").hidden = false; $("nav").hidden = true; $("who").hidden = true;
  $("page").replaceChildren();
  $("login-key").focus();
}

function showShell() {
  $("login").hidden = true; $("nav").hidden = false; $("who").hidden = false;
  $("who-name").textContent = caller.name;
  $("who-role").textContent = caller.role;
  for (const link of $("nav").querySelectorAll("a")) link.hidden = !caller.may(link.dataset.role || "robot");
}

async function route() {
  if (stopPage) { stopPage(); stopPage = null; }
  const [name, ...args] = (location.hash.replace(/^#\/?/, "") || "atlases").split("/").map(decodeURIComponent);
  const page = PAGES[name] && caller.may(PAGES[name].role) ? name : "atlases";
  for (const link of $("nav").querySelectorAll("a")) link.classList.toggle("active", link.dataset.page === page);
  const container = $("page");
  container.replaceChildren();
  container.dataset.page = page;
  try {
    stopPage = (await PAGES[page].render(container, { caller, args })) || null;
  } catch (err) {
    container.append(errorBox(err));
    if (err instanceof ApiError && err.status === 401) { session.key = ""; showLogin(); }
  }
}

async function start() {
  $("login").addEventListener("submit", async (event) => {
    event.preventDefault();
    if (await signIn($("login-key").value.trim())) { showShell(); route(); }
  });
  $("logout").addEventListener("click", () => {
    session.key = ""; forgetThumbnails(); sessionStorage.clear();
    if (stopPage) { stopPage(); stopPage = null; }
    showLogin();
  });
  window.addEventListener("hashchange", () => { if (!$("nav").hidden) route(); });
  // A key kept for this tab, or an open service (no keys yet) signs in by itself.
  if (await signIn(session.key)) { showShell(); route(); } else { $("login-error").textContent = ""; showLogin(); }
}

start();
