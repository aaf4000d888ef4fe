// rigd operator dashboard. Plain ES module, no build step, no network
// beyond the daemon that serves it.
import { drawPlot } from "/hemisphere.js";

const API = "/api/v1";
const TOKEN_KEY = "rigd-token";
const $ = (id) => document.getElementById(id);

const state = {
  rig: null,
  plans: [],
  runs: [], // the history page shown
  shownView: null, // the shown run when it is not on that page
  // The history's paging and filters (GET /runs?limit&cursor&sample&state&plan):
  // cursors[i] opens page i (null: the first), `next` the page after this one.
  hist: { cursors: [null], page: 0, next: null, total: 0, sample: "", state: "", plan: "", seq: 0 },
  activeId: null,
  shownId: null, // the run shown in the "Active run" card
  steps: [], // its steps
  stepsRun: null,
  done: new Set(),
  current: null, // last captured step
  queue: [],
  testFrame: false, // the preview shows a manual test frame
  peers: [], // this rig and its peers (GET /peers)
  peerBusy: {}, // peer name → the command on its way to it
};

// ---------------------------------------------------------------- API

class ApiError extends Error {
  constructor(status, error, detail) {
    super(`${error}: ${detail}`);
    this.status = status;
    this.error = error;
    this.detail = detail;
  }
}

function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

async function api(method, path, body, retried = false) {
  const mutating = method !== "GET";
  if (mutating && !token() && !retried) {
    await askToken("Enter the API token to continue.");
    if (!token()) throw new ApiError(401, "unauthorized", "no API token entered");
    retried = true;
  }
  const headers = {};
  if (token()) headers.Authorization = `Bearer ${token()}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let res;
  try {
    res = await fetch(API + path, {
      method,
      headers,
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (e) {
    throw new ApiError(0, "network", `cannot reach the daemon (${e.message})`);
  }
  if (res.status === 401 && !retried) {
    const saved = await askToken("The daemon refused the token (401). Enter the API token.");
    if (saved) return api(method, path, body, true);
  }
  if (!res.ok) {
    let err = { error: `http_${res.status}`, detail: res.statusText };
    try {
      err = await res.json();
    } catch (_) {
      /* not JSON */
    }
    throw new ApiError(res.status, err.error, err.detail);
  }
  if (res.status === 204) return null;
  const text = await res.text();
  return text ? JSON.parse(text) : null;
}

// ------------------------------------------------------- token dialog

let tokenWaiters = [];

function askToken(why) {
  const dlg = $("token-dialog");
  $("token-why").textContent = why || "";
  $("token-input").value = token();
  if (!dlg.open) dlg.showModal();
  $("token-input").focus();
  return new Promise((resolve) => tokenWaiters.push(resolve));
}

function setupTokenDialog() {
  const dlg = $("token-dialog");
  dlg.addEventListener("close", () => {
    let saved = false;
    if (dlg.returnValue === "save") {
      const t = $("token-input").value.trim();
      if (t) {
        localStorage.setItem(TOKEN_KEY, t);
        saved = true;
        log("info", "API token saved in this browser");
      }
    }
    const waiters = tokenWaiters;
    tokenWaiters = [];
    for (const w of waiters) w(saved);
  });
  $("token-open").addEventListener("click", () => askToken());
}

// ------------------------------------------------------------ helpers

function fmtDuration(s) {
  if (s == null || !isFinite(s)) return "—";
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600);
  const m = Math.floor((s % 3600) / 60);
  const sec = s % 60;
  if (h > 0) return `${h} h ${m} min`;
  if (m > 0) return `${m} min ${sec} s`;
  return `${sec} s`;
}

function fmtTime(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  return isNaN(d) ? iso : d.toLocaleString();
}

function text(tag, content, attrs = {}) {
  const e = document.createElement(tag);
  if (content != null) e.textContent = content;
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}

function showMessage(msg, kind = "error") {
  const m = $("message");
  m.textContent = msg;
  m.dataset.kind = kind;
  m.hidden = false;
  clearTimeout(showMessage.t);
  showMessage.t = setTimeout(() => (m.hidden = true), kind === "error" ? 12000 : 4000);
}

function errText(e) {
  return e instanceof ApiError ? `${e.error}: ${e.detail}` : String(e);
}

/** Runs `fn` at most once per `ms`, trailing call guaranteed. */
function throttle(fn, ms) {
  let last = 0;
  let timer = null;
  return () => {
    const now = Date.now();
    const wait = last + ms - now;
    if (wait <= 0) {
      last = now;
      fn();
    } else if (!timer) {
      timer = setTimeout(() => {
        timer = null;
        last = Date.now();
        fn();
      }, wait);
    }
  };
}

// ----------------------------------------------------------- loaders

let rigSeq = 0;
async function loadRig() {
  const seq = ++rigSeq;
  try {
    const rig = await api("GET", "/rig");
    if (seq !== rigSeq) return; // a later request is on its way
    state.rig = rig;
    state.activeId = state.rig.active_run;
    renderRig();
  } catch (e) {
    showMessage(`rig: ${errText(e)}`);
  }
}

async function loadPlans() {
  try {
    const list = await api("GET", "/plans");
    state.plans = list.plans;
    renderPlans();
    // The daemon solves its plans in the background after it starts.
    if (state.plans.some((p) => !p.ready)) setTimeout(loadPlans, 1000);
  } catch (e) {
    showMessage(`plans: ${errText(e)}`);
  }
}

const HISTORY_PAGE = 50;

/** The query of the history page shown: its cursor and the filters. */
function historyQuery() {
  const h = state.hist;
  const q = new URLSearchParams({ limit: String(HISTORY_PAGE) });
  const cursor = h.cursors[h.page];
  if (cursor) q.set("cursor", cursor);
  for (const k of ["sample", "state", "plan"]) if (h[k]) q.set(k, h[k]);
  return q.toString();
}

function historyFiltered() {
  const h = state.hist;
  return Boolean(h.sample || h.state || h.plan);
}

// Only the page shown is fetched: the daemon may hold tens of thousands of runs.
async function loadRuns() {
  const h = state.hist;
  const seq = ++h.seq;
  try {
    const list = await api("GET", `/runs?${historyQuery()}`);
    if (seq !== h.seq) return; // a newer page or filter was asked for meanwhile
    if (!list.runs.length && h.page > 0) {
      // The page emptied (runs removed, filters changed): back to the first.
      h.page = 0;
      h.cursors = [null];
      return loadRuns();
    }
    state.runs = list.runs;
    h.next = list.next || null;
    h.total = list.total || 0;
    state.activeId = list.active;
    const shown = list.active || state.shownId || (list.runs[0] && list.runs[0].id) || null;
    if (shown !== state.shownId) {
      state.shownId = shown;
      state.steps = [];
      state.stepsRun = null;
    }
    renderHistory();
    if (shown && !shownRun()) await loadRun(shown);
    renderRun();
    if (state.shownId && state.stepsRun !== state.shownId) await loadSteps();
  } catch (e) {
    showMessage(`runs: ${errText(e)}`);
  }
}

function historyPage(delta) {
  const h = state.hist;
  if (delta > 0) {
    if (!h.next) return;
    h.cursors = h.cursors.slice(0, h.page + 1);
    h.cursors.push(h.next);
    h.page += 1;
  } else {
    if (h.page === 0) return;
    h.page -= 1;
  }
  loadRuns();
}

function historyFilter() {
  const h = state.hist;
  h.sample = $("history-sample").value.trim();
  h.state = $("history-state").value;
  h.plan = $("history-plan").value.trim();
  h.page = 0;
  h.cursors = [null];
  loadRuns();
}

function setupHistory() {
  const typed = debounce(historyFilter, 300);
  $("history-sample").addEventListener("input", typed);
  $("history-plan").addEventListener("input", typed);
  $("history-state").addEventListener("change", historyFilter);
  $("history-filters").addEventListener("submit", (e) => {
    e.preventDefault();
    historyFilter();
  });
  $("history-prev").addEventListener("click", () => historyPage(-1));
  $("history-next").addEventListener("click", () => historyPage(1));
}

function debounce(fn, ms) {
  let timer = null;
  return (...args) => {
    clearTimeout(timer);
    timer = setTimeout(() => fn(...args), ms);
  };
}

async function loadRun(id) {
  try {
    const run = await api("GET", `/runs/${encodeURIComponent(id)}`);
    upsertRun(run);
  } catch (e) {
    if (!(e instanceof ApiError && e.status === 404)) showMessage(`run: ${errText(e)}`);
  }
}

async function loadSteps() {
  const id = state.shownId;
  if (!id) return;
  try {
    const s = await api("GET", `/runs/${encodeURIComponent(id)}/steps`);
    if (id !== state.shownId) return;
    state.steps = s.steps;
    state.stepsRun = id;
    state.done = new Set(s.steps.filter((x) => x.done).map((x) => x.index));
    // The current step: the highest index done (steps are captured in order).
    let cur = null;
    for (const x of s.steps) if (x.done && (!cur || x.index > cur.index)) cur = x;
    state.current = cur;
    drawHemisphere();
    refreshPreview();
  } catch (e) {
    showMessage(`steps: ${errText(e)}`);
  }
}

async function loadQueue() {
  try {
    const q = await api("GET", "/queue");
    state.queue = q.items;
    renderQueue();
  } catch (e) {
    showMessage(`queue: ${errText(e)}`);
  }
}

async function loadAll() {
  await Promise.all([loadRig(), loadRuns(), loadQueue(), state.plans.length ? null : loadPlans(), loadTradeoff(), loadPeers()]);
}

// ------------------------------------------------------------- peers

// With peers (`rigd serve --peers`), the "Rigs" card lists every rig,
// asked again every second; the daemon answers from memory (it polls the
// peers itself), so a dead peer never slows this down.
let peersTimer = null;
let peersSeq = 0;
async function loadPeers() {
  const seq = ++peersSeq;
  try {
    const list = await api("GET", "/peers");
    if (seq === peersSeq) {
      state.peers = list.peers;
      renderPeers();
    }
  } catch (e) {
    // Our own daemon did not answer: the indicator at the top says so.
    $("rigs-card").dataset.error = errText(e);
  }
  clearTimeout(peersTimer);
  if (state.peers.length > 1) peersTimer = setTimeout(loadPeers, 1000);
}

let peersShown = "";
function renderPeers() {
  const peers = state.peers;
  const card = $("rigs-card");
  card.hidden = peers.length < 2;
  delete card.dataset.error;
  if (card.hidden) return;
  // Rebuilt only when something shown changed (buttons keep their focus).
  const key = JSON.stringify([peers.map((p) => ({ ...p, last_seen: null, seen_ago_s: p.reachable ? null : Math.round(p.seen_ago_s ?? -1) })), state.peerBusy]);
  if (key === peersShown) return;
  peersShown = key;
  const tbody = $("rigs").tBodies[0];
  tbody.replaceChildren(...peers.map(peerRow));
}

function peerRow(p) {
  const tr = text("tr", null, { "data-peer": p.name, "data-reachable": String(p.reachable) });
  if (!p.reachable) tr.className = "unreachable";
  const name = text("td");
  name.append(text("strong", p.name));
  if (p.profile) name.append(text("div", `${p.profile}${p.sim ? " (simulated)" : ""}`, { class: "muted small" }));
  const daemon = text("td");
  const reach = p.local ? "this daemon" : p.reachable ? "reachable" : "unreachable";
  daemon.append(text("span", reach, { class: "badge", "data-testid": "peer-reachable", "data-state": p.reachable ? "reachable" : "unreachable" }));
  daemon.append(text("div", p.url, { class: "mono muted small" }));
  if (!p.reachable) {
    const seen = p.seen_ago_s != null ? `last seen ${fmtDuration(p.seen_ago_s)} ago` : "never seen";
    daemon.append(text("div", `${p.error || "no answer"}; ${seen}`, { class: "fault-text small", "data-testid": "peer-error" }));
  }
  const st = text("td");
  if (p.state) st.append(text("span", p.state, { class: "badge", "data-state": p.state, "data-testid": "peer-state" }));
  else st.append("—");
  const run = p.active_run;
  const runCell = text("td", null, { "data-testid": "peer-run" });
  if (run) {
    const pct = run.steps_total ? ((100 * run.steps_done) / run.steps_total).toFixed(1) : "0";
    const bar = text("progress", null, { "aria-label": `${p.name}: frames captured` });
    bar.max = Math.max(run.steps_total, 1);
    bar.value = run.steps_done;
    runCell.dataset.done = String(run.steps_done);
    runCell.append(text("div", `${run.id}`, { class: "mono" }), bar,
      text("div", `${run.state}: ${run.steps_done} / ${run.steps_total} frames (${pct} %)${run.eta_wall_s != null && ["running", "preparing"].includes(run.state) ? ` · ≈ ${fmtDuration(run.eta_wall_s)} left` : ""}`, { class: "small" }));
    if (run.reason) runCell.append(text("div", run.reason, { class: "muted small" }));
  } else runCell.append(p.state ? "none" : "—");
  const queue = text("td", p.queue_length == null ? "—" : String(p.queue_length), { "data-testid": "peer-queue" });
  const faults = text("td", null, { "data-testid": "peer-faults" });
  if (p.faults.length) for (const f of p.faults) faults.append(text("div", f, { class: "fault-text small" }));
  else faults.append(p.state ? "none" : "—");
  const actions = text("td");
  if (!p.local) {
    actions.append(text("a", "Open", { href: `${p.url}/`, target: "_blank", rel: "noopener", "data-testid": "peer-open", title: `${p.name}'s own dashboard` }));
    const busy = state.peerBusy[p.name];
    const live = p.reachable && run && !busy;
    const pause = text("button", "Pause", { type: "button", class: "small", "data-testid": "peer-pause", "aria-label": `Pause ${p.name}'s run` });
    pause.disabled = !(live && ["running", "preparing"].includes(run.state));
    pause.addEventListener("click", () => peerCommand(p, "pause"));
    const stop = text("button", "Stop…", { type: "button", class: "small danger", "data-testid": "peer-abort", "aria-label": `Stop ${p.name}'s run` });
    stop.disabled = !(live && ["running", "preparing", "paused"].includes(run.state));
    stop.addEventListener("click", () => peerCommand(p, "abort"));
    actions.append(" ", pause, " ", stop);
  }
  tr.append(name, daemon, st, runCell, queue, faults, actions);
  return tr;
}

// Pause or stop (abort) a peer's active run, through this daemon.
async function peerCommand(p, cmd) {
  const run = p.active_run;
  if (!run) return;
  if (cmd === "abort" && !confirm(`Stop (abort) run ${run.id} on ${p.name}? Its frames so far are kept; it cannot be resumed.`)) return;
  state.peerBusy[p.name] = cmd;
  renderPeers();
  try {
    const r = await api("POST", `/peers/${encodeURIComponent(p.name)}/${cmd}`);
    log("info", `${cmd} sent to ${p.name}'s run ${(r && r.run && r.run.id) || run.id}`);
  } catch (e) {
    showMessage(`${p.name}: ${cmd}: ${errText(e)}`);
  } finally {
    delete state.peerBusy[p.name];
    loadPeers();
  }
}

// ------------------------------------------------------ trade-off plot

async function loadTradeoff() {
  const plot = $("tradeoff-plot");
  try {
    const [r, fig] = await Promise.all([api("GET", "/tradeoff"), api("GET", "/tradeoff/figure")]);
    showTradeoffFigure(plot, r, fig);
    plot.hidden = false;
    const caption = $("tradeoff-caption");
    caption.textContent =
      `${r.profile}, scene ${r.scene}: ${r.rows.length} rows, ${r.texture}² textures, ${r.held_out} held-out pairs`;
    // The knee of each family's curve, computed by the report.
    for (const line of r.summary || []) caption.append(text("div", line, { class: "tradeoff-summary" }));
  } catch (e) {
    plot.hidden = true;
    $("tradeoff-caption").textContent = e.status === 404 ? e.detail : `trade-off: ${errText(e)}`;
  }
  const sel = $("tradeoff-scene");
  if (!sel.options.length) {
    try {
      const scenes = await api("GET", "/sim/scenes");
      for (const sc of scenes.scenes || scenes) sel.append(text("option", sc.name, { value: sc.name }));
      if ([...sel.options].some((o) => o.value === "corduroy")) sel.value = "corduroy";
    } catch (e) {
      // The select stays empty and the daemon picks its scene.
      $("tradeoff-status").textContent = `scenes: ${errText(e)}`;
    }
  }
}

const SVG_NS = "http://www.w3.org/2000/svg";

// The figure inline, with a hit target over every point: hover shows the
// row's values, a click on a plan puts that plan into the start form.
function showTradeoffFigure(plot, report, fig) {
  const doc = new DOMParser().parseFromString(fig.svg, "image/svg+xml");
  const svg = document.importNode(doc.documentElement, true);
  svg.removeAttribute("width");
  svg.removeAttribute("height");
  svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", `Trade-off figure: ${fig.panels.map((p) => p.title).join("; ")}`);
  for (const [i, pt] of fig.points.entries()) {
    const row = report.rows[pt.row];
    const panel = fig.panels[pt.panel];
    // The point and its label both answer: points can coincide (H1 and
    // H2 on a rig that reaches every direction), their labels cannot.
    const point = document.createElementNS(SVG_NS, "circle");
    point.setAttribute("cx", pt.x);
    point.setAttribute("cy", pt.y);
    point.setAttribute("r", 9);
    const targets = [point];
    if (pt.label) {
      const [x0, y0, x1, y1] = pt.label;
      const label = document.createElementNS(SVG_NS, "rect");
      for (const [k, v] of Object.entries({ x: x0, y: y0, width: x1 - x0, height: y1 - y0 })) label.setAttribute(k, v);
      targets.push(label);
    }
    for (const hit of targets) {
      hit.setAttribute("class", `tradeoff-hit ${hit === point ? "point" : "label"}${isPlanPoint(panel, row) ? " plan" : ""}`);
      hit.dataset.point = String(i);
      hit.dataset.family = panel.family;
      hit.dataset.setting = row.setting;
      hit.addEventListener("mouseenter", () => showTradeoffTip(plot, svg, pt, row, panel));
      hit.addEventListener("mouseleave", () => ($("tradeoff-tip").hidden = true));
      if (isPlanPoint(panel, row)) hit.addEventListener("click", () => useTradeoffPlan(svg, point, row));
      svg.append(hit);
    }
  }
  plot.replaceChildren(svg);
}

function isPlanPoint(panel, row) {
  return panel.family === "plans" && Array.isArray(row.directions);
}

function fmtBytes(b) {
  if (b == null) return "—";
  if (b >= 1e9) return `${(b / 1e9).toFixed(1)} GB`;
  if (b >= 1e6) return `${(b / 1e6).toFixed(1)} MB`;
  return `${(b / 1e3).toFixed(0)} kB`;
}

// A row's error with its standard error, in the row's unit.
function fmtRowError(row) {
  if (row.error == null) return "—";
  const [scale, digits, unit] =
    row.unit === "relative" ? [100, 1, " %"] : row.unit === "degrees" ? [1, 2, "°"] : [1, 3, ` ${row.unit}`];
  const e = (row.error * scale).toFixed(digits);
  return row.spread == null ? `${e}${unit}` : `${e} ± ${(row.spread * scale).toFixed(digits)}${unit}`;
}

function showTradeoffTip(plot, svg, pt, row, panel) {
  const tip = $("tradeoff-tip");
  const lines = [
    `${panel.family}: ${row.setting}`,
    `error ${fmtRowError(row)}`,
    row.near_mirror != null
      ? `within 10° of the mirror ${fmtRowError({ ...row, error: row.near_mirror.error, spread: row.near_mirror.spread })}`
      : null,
    row.clipped_share != null ? `${(100 * row.clipped_share).toFixed(2)} % of texels clipped` : null,
    row.physical_s != null ? `physical time ${fmtDuration(row.physical_s)}` : null,
    row.images != null ? `${row.images} images` : null,
    row.bytes != null ? `${fmtBytes(row.bytes)}${panel.family === "pca" ? " compressed" : " raw"}` : null,
    row.coverage != null ? `covers ${(100 * row.coverage).toFixed(1)} % of the sample` : null,
    row.compute_s != null && row.physical_s == null ? `render ${row.compute_s.toFixed(3)} s` : null,
    pt.frontier ? "on the frontier" : "dominated: another setting is both cheaper and better",
    isPlanPoint(panel, row) ? "click: use this plan in the start form" : null,
  ].filter(Boolean);
  tip.replaceChildren(...lines.map((l) => text("div", l)));
  // The point's place on screen, from the SVG's own coordinates.
  const box = svg.getBoundingClientRect();
  const host = plot.parentElement.getBoundingClientRect();
  const scale = box.width / Number(svg.viewBox.baseVal.width || box.width);
  tip.style.left = `${box.left - host.left + pt.x * scale + 12}px`;
  tip.style.top = `${box.top - host.top + pt.y * scale + 12}px`;
  tip.hidden = false;
}

// Puts a measured plan into the start form: the named plan where the
// daemon has it, else its directions as custom directions.
function useTradeoffPlan(svg, hit, row) {
  for (const h of svg.querySelectorAll(".tradeoff-hit.chosen")) h.classList.remove("chosen");
  hit.classList.add("chosen");
  const sel = $("plan");
  const named = row.plan && state.plans.find((p) => p.name === row.plan && p.ready && p.fits);
  if (named) {
    sel.value = row.plan;
  } else {
    sel.value = "__custom";
    $("custom-dirs").value = row.directions.map((d) => `${d.theta_deg} ${d.phi_deg}`).join("\n");
  }
  state.planChosen = true;
  planChanged();
  const info = $("plan-info");
  info.textContent =
    `From the trade-off: ${row.setting}, ${row.images} images, about ${fmtDuration(row.physical_s)} physical, ` +
    `${fmtBytes(row.bytes)} raw, held-out error ${fmtRowError(row)}` +
    (named ? `. ${info.textContent}` : "");
  $("run-form").scrollIntoView({ block: "nearest" });
}

async function startTradeoff() {
  const btn = $("tradeoff-start");
  btn.disabled = true;
  try {
    const body = $("tradeoff-scene").value ? { scene: $("tradeoff-scene").value } : {};
    const r = await api("POST", "/tradeoff", body);
    $("tradeoff-status").textContent = `computing for ${r.scene}…`;
  } catch (e) {
    $("tradeoff-status").textContent = errText(e);
    btn.disabled = false;
  }
}

function onTradeoffEvent(e) {
  const st = $("tradeoff-status");
  if (e.state === "computing") st.textContent = `computing: ${e.step}`;
  else if (e.state === "started") st.textContent = `computing for ${e.scene}…`;
  else if (e.state === "failed") st.textContent = `failed: ${e.error}`;
  else if (e.state === "done") {
    st.textContent = `done: ${e.rows} rows`;
    loadTradeoff();
  }
  $("tradeoff-start").disabled = e.state === "started" || e.state === "computing";
}

function upsertRun(run) {
  const i = state.runs.findIndex((r) => r.id === run.id);
  if (i >= 0) state.runs[i] = run;
  else if (state.hist.page === 0 && !historyFiltered()) {
    // A new run belongs at the top of the first page.
    state.runs.unshift(run);
    if (state.runs.length > HISTORY_PAGE) state.runs.pop();
  }
  if (run.id === state.shownId) state.shownView = run;
  if (run.active) state.activeId = run.id;
  else if (state.activeId === run.id) state.activeId = null;
  renderHistory();
  if (run.id === state.shownId) renderRun();
}

const refreshRig = throttle(loadRig, 1000);
const refreshShownRun = throttle(() => state.shownId && loadRun(state.shownId), 1000);
const drawHemisphereSoon = throttle(() => drawHemisphere(), 250);
const renderHistorySoon = throttle(() => renderHistory(), 1000);
const refreshPreview = throttle(() => {
  const img = $("preview");
  const cur = state.current;
  // A manual test frame stays until a run is active again.
  if (state.testFrame && !state.activeId) return;
  state.testFrame = false;
  if (!cur || !state.shownId) {
    img.removeAttribute("src");
    img.alt = "No frame captured yet";
    $("preview-caption").textContent = "latest frame";
    return;
  }
  const src = `${API}/runs/${encodeURIComponent(state.shownId)}/frames/${cur.index}/preview`;
  if (img.getAttribute("src") !== src) {
    img.src = src;
    img.alt = `Preview of frame ${cur.index}`;
    $("preview-caption").textContent = `frame ${cur.index}: light θ ${cur.light.theta_deg.toFixed(1)}° φ ${cur.light.phi_deg.toFixed(1)}°, view θ ${cur.view.theta_deg.toFixed(1)}° φ ${cur.view.phi_deg.toFixed(1)}°`;
  }
}, 1000);

// ---------------------------------------------------------- renderers

function renderRig() {
  const rig = state.rig;
  if (!rig) return;
  $("profile").textContent = rig.profile + (rig.sim ? ` (simulated, ${rig.sim_speed}×)` : "");
  $("rig-desc").textContent = rig.description;
  const badge = $("rig-state");
  badge.textContent = `rig ${rig.state}`;
  badge.dataset.state = rig.state;
  fillManualSelects(rig);
  const tbody = $("rig").tBodies[0];
  tbody.replaceChildren();
  for (const d of rig.devices) {
    const tr = document.createElement("tr");
    tr.dataset.device = d.name;
    if (d.fault) tr.className = "fault";
    tr.append(text("td", d.name), text("td", `${d.kind} (${d.protocol})`));
    const flags = [];
    flags.push(d.connected ? "connected" : "disconnected");
    if (d.homed != null) flags.push(d.homed ? "homed" : "not homed");
    if (d.homing === false) flags.push("no homing: zeroed by hand at its 0° mark");
    if (d.busy) flags.push("busy");
    const st = text("td", flags.join(", "));
    if (d.fault) {
      const f = text("div", `FAULT: ${d.fault}`, { class: "fault-text", "data-testid": "fault" });
      st.append(f);
    }
    tr.append(st);
    let pos = "—";
    if (d.position_deg != null) pos = `${d.position_deg.toFixed(2)}°`;
    else if (d.joints) pos = Object.entries(d.joints).map(([j, v]) => `${j} ${Number(v).toFixed(1)}°`).join(", ");
    else if (d.on != null) pos = d.on ? "lamp ON" : "lamp off";
    else if (d.camera) {
      const c = d.camera;
      pos = `exposure ${c.exposure_s} s, ${c.bit_depth}-bit, ${c.resolution ? c.resolution.join("×") : "?"} (sim ${c.sim_frame_size ? c.sim_frame_size.join("×") : "?"})`;
    }
    const td = text("td", pos);
    if (d.on === true) td.className = "lamp-on";
    tr.append(td);
    tbody.append(tr);
  }
}

function renderPlans() {
  const sel = $("plan");
  const prev = sel.value;
  sel.replaceChildren();
  for (const p of state.plans) {
    const label = !p.ready
      ? `${p.name} (computing…)`
      : p.fits ? `${p.name} (${p.steps_total} images)` : `${p.name} — does not fit`;
    const o = text("option", label, { value: p.name });
    if (!p.ready || !p.fits) {
      o.disabled = true;
      o.title = p.error || "";
    }
    sel.append(o);
  }
  sel.append(text("option", "custom directions…", { value: "__custom" }));
  const firstFit = state.plans.find((p) => p.ready && p.fits);
  // Keep the operator's choice; until they make one, the first plan that fits.
  const prevUsable = state.planChosen && (prev === "__custom" || state.plans.some((p) => p.name === prev && p.ready && p.fits));
  sel.value = prevUsable ? prev : firstFit ? firstFit.name : "__custom";
  planChanged();
}

/** How the start form names an exposure policy. */
function policyLabel(e) {
  const p = e.policy;
  const label =
    p.policy === "brackets"
      ? `brackets ${p.exposures_s.map((t) => Number(t.toPrecision(4))).join(", ")} s`
      : p.policy === "auto"
        ? "auto: again shorter where the sample clips"
        : "single";
  return e.profile_default ? `${label} (profile default)` : label;
}

/** The exposure policies the plans offer (the same for every plan of the
 * rig), kept when a custom plan is chosen; the operator's choice stays. */
function renderPolicies(estimates) {
  const sel = $("exposure-policy");
  const prev = sel.value;
  const values = estimates.map((e) => JSON.stringify(e.policy));
  if ([...sel.options].map((o) => o.value).join("\n") !== values.join("\n")) {
    sel.replaceChildren(...estimates.map((e, i) => text("option", policyLabel(e), { value: values[i] })));
  }
  if (values.includes(prev)) sel.value = prev;
}

function planChanged() {
  const v = $("plan").value;
  $("custom-field").hidden = v !== "__custom";
  const p = state.plans.find((x) => x.name === v);
  const estimates = (p && p.exposure_estimates) || [];
  const anyPlan = state.plans.find((x) => x.exposure_estimates && x.exposure_estimates.length);
  renderPolicies(estimates.length ? estimates : anyPlan ? anyPlan.exposure_estimates : []);
  const chosen = estimates.find((e) => JSON.stringify(e.policy) === $("exposure-policy").value);
  const cost = chosen || p;
  const atLeast = chosen && chosen.lower_bound ? "at least " : "about ";
  $("plan-info").textContent = p
    ? `${p.steps_total} images, ${p.infeasible_total} infeasible; ${atLeast}${fmtDuration(cost.estimated_physical_s)} physical (${fmtDuration(cost.estimated_wall_s)} at this simulation speed); ${fmtBytes(cost.raw_bytes)} raw, ${fmtBytes(p.image_bytes)} an image`
    : v === "__custom"
      ? "Every direction is used as light and as view."
      : "";
}

function shownRun() {
  const onPage = state.runs.find((r) => r.id === state.shownId);
  if (onPage) return onPage;
  const v = state.shownView;
  return v && v.id === state.shownId ? v : null;
}

function renderRun() {
  const run = shownRun();
  const badge = $("run-state");
  if (!run) {
    $("run-id").textContent = "no run yet";
    badge.textContent = "—";
    delete badge.dataset.state;
    $("progress").max = 1;
    $("progress").value = 0;
    $("progress-text").textContent = "—";
    for (const b of ["pause", "resume", "abort"]) $(b).disabled = true;
    $("run-reason").hidden = true;
    return;
  }
  $("run-h").textContent = run.active ? "Active run" : "Last run";
  $("run-id").textContent = `${run.id} — ${run.sample}, plan ${run.plan}`;
  badge.textContent = run.state;
  badge.dataset.state = run.state;
  const total = run.steps_total || 0;
  const done = Math.max(run.steps_done || 0, run.id === state.stepsRun ? state.done.size : 0);
  const prog = $("progress");
  prog.max = Math.max(total, 1);
  prog.value = done;
  prog.dataset.done = String(done);
  prog.dataset.total = String(total);
  const pct = total ? ((100 * done) / total).toFixed(1) : "0";
  let eta = "";
  if (run.eta_physical_s != null && run.active) {
    eta = ` · ETA ${fmtDuration(run.eta_physical_s)} physical`;
    if (run.eta_wall_s != null) eta += ` (≈ ${fmtDuration(run.eta_wall_s)} wall)`;
  }
  // Physical time is the rig model's; the host only sets how fast it goes.
  let pace = "";
  if (run.active && run.pace && run.pace.behind) {
    pace = ` · host behind: ${Math.round(run.pace.achieved_speed)}× of ${Math.round(run.pace.asked_speed)}× asked`;
  }
  $("progress-text").textContent = `${done} / ${total} frames (${pct} %)${eta} · ${fmtDuration(run.physical_s)} captured${pace}`;
  const reason = $("run-reason");
  reason.hidden = !run.reason;
  reason.textContent = run.reason ? `Reason: ${run.reason}` : "";
  reason.classList.toggle("bad", ["failed", "aborted", "interrupted"].includes(run.state) || /fault|estop|stop/i.test(run.reason || ""));
  const live = run.active;
  $("pause").disabled = !(live && ["running", "preparing"].includes(run.state));
  // A live paused run, or one with no engine that can be continued
  // (paused after a restart, interrupted, failed but resumable).
  $("resume").disabled = !((live && run.state === "paused") || (!live && run.resumable));
  $("abort").disabled = !(live || run.resumable);
}

function drawHemisphere() {
  const steps = state.stepsRun === state.shownId ? state.steps : [];
  drawPlot($("hemi-lights"), "lights", steps, state.done, state.current);
  drawPlot($("hemi-views"), "views", steps, state.done, state.current);
}

function renderQueue() {
  const tbody = $("queue").tBodies[0];
  tbody.replaceChildren();
  state.queue.forEach((item, i) => {
    const tr = document.createElement("tr");
    tr.dataset.item = item.id;
    const plan = typeof item.request.plan === "string" ? item.request.plan : item.request.plan.name || "custom";
    tr.append(text("td", String(i + 1)), text("td", item.request.sample), text("td", plan), text("td", fmtTime(item.created_at)));
    const td = document.createElement("td");
    const b = text("button", "Remove", { type: "button", class: "small", "data-testid": "queue-delete", "aria-label": `Remove ${item.request.sample} from the queue` });
    b.addEventListener("click", async () => {
      b.disabled = true;
      try {
        await api("DELETE", `/queue/${encodeURIComponent(item.id)}`);
        await loadQueue();
      } catch (e) {
        showMessage(`remove from queue: ${errText(e)}`);
        b.disabled = false;
      }
    });
    td.append(b);
    tr.append(td);
    tbody.append(tr);
  });
  $("queue-empty").hidden = state.queue.length > 0;
}

function renderHistory() {
  const tbody = $("history").tBodies[0];
  tbody.replaceChildren();
  const h = state.hist;
  const first = h.page * HISTORY_PAGE;
  $("history-pos").textContent = state.runs.length
    ? `${first + 1}–${first + state.runs.length} of ${h.total}`
    : `0 of ${h.total}`;
  $("history-prev").disabled = h.page === 0;
  $("history-next").disabled = !h.next;
  $("history-empty").hidden = state.runs.length > 0;
  const plans = new Set([...state.plans.map((p) => p.name), ...state.runs.map((r) => r.plan)]);
  const list = $("history-plans");
  if (list.children.length !== plans.size) {
    list.replaceChildren(...[...plans].sort().map((p) => text("option", "", { value: p })));
  }
  for (const r of state.runs) {
    const tr = document.createElement("tr");
    tr.dataset.runId = r.id;
    tr.dataset.state = r.state;
    if (r.id === state.shownId) tr.className = "shown";
    const idCell = document.createElement("td");
    const show = text("button", r.id, { type: "button", class: "link mono", title: "Show this run above" });
    show.addEventListener("click", () => {
      state.shownId = r.id;
      state.stepsRun = null;
      state.steps = [];
      state.current = null;
      renderRun();
      renderHistory();
      loadSteps();
    });
    idCell.append(show);
    const st = text("td", r.state, { class: `state state-${r.state}` });
    if (r.reason) st.title = r.reason;
    tr.append(idCell, text("td", r.sample), text("td", r.plan), st, text("td", `${r.steps_done} / ${r.steps_total}`), text("td", fmtTime(r.started_at)), text("td", fmtTime(r.finished_at)), processCell(r));
    const links = document.createElement("td");
    const base = `${API}/runs/${encodeURIComponent(r.id)}`;
    if (["completed", "aborted"].includes(r.state)) {
      links.append(text("a", "manifest", { href: `${base}/manifest`, target: "_blank", rel: "noopener" }), " ");
    }
    links.append(text("a", "steps", { href: `${base}/steps`, target: "_blank", rel: "noopener" }));
    if (r.steps_done > 0) {
      links.append(" ", text("a", "first frame", { href: `${base}/frames/0`, target: "_blank", rel: "noopener" }));
    }
    if (r.processed) {
      links.append(" ", text("a", "view", {
        href: `/viewer/${encodeURIComponent(r.id)}`, "data-testid": "open-viewer",
        title: r.processed === "btf" ? "Relight the BTF on a mesh" : "Bump-mapped albedo and normals",
      }));
    }
    tr.append(links);
    tbody.append(tr);
  }
}

/** Where a run's process job is: its latest `process` event, else the job
 * in the run's view; null without a job. */
function processStatus(r) {
  if (r.processEvent) return r.processEvent;
  const job = r.processing;
  if (!job) return null;
  const cur = job.steps.find((s) => s.state === "running" || s.state === "failed") || null;
  return {
    state: job.state,
    step: cur && cur.step,
    done: cur && cur.done,
    total: cur && cur.total,
    eta_s: cur && cur.eta_s,
    detail: cur && cur.detail,
    steps_done: job.steps.filter((s) => s.state === "done").length,
    steps_total: job.steps.length,
    error: job.error,
    cancelling: !!job.cancelling,
    streamed: job.streamed || 0,
    slots_ahead: job.slots_ahead || 0,
  };
}

function processCell(r) {
  const td = text("td", null, { class: "processing", "data-testid": "processing" });
  const p = processStatus(r);
  if (p && (p.state === "queued" || p.state === "running")) {
    const bar = text("progress", null, { "data-testid": "process-progress", "aria-label": `Processing ${r.id}` });
    bar.max = p.total || 1;
    bar.value = p.done || 0;
    let label = "queued";
    if (p.state === "queued" && p.streamed > 0) {
      // Frames registered while the capture runs.
      bar.max = r.steps_total || 1;
      bar.value = p.streamed;
      label = `rectify during the capture ${p.streamed}/${r.steps_total}`;
      if (p.slots_ahead > 0) label += `, ${p.slots_ahead} view slots compressed`;
    }
    if (p.state === "running" && p.step) {
      label = `${p.step} ${p.done ?? 0}/${p.total ?? "?"}`;
      if (p.eta_s != null) label += `, ${fmtDuration(p.eta_s)} left`;
    }
    td.append(bar, text("span", `step ${Math.min(p.steps_done + 1, p.steps_total)}/${p.steps_total}: ${label}`, { class: "process-status" }));
    // On Slurm: the job and its array, a task submitted again.
    if (p.state === "running" && p.detail) {
      td.append(text("div", p.detail, { class: "process-detail", "data-testid": "process-detail" }));
    }
    const cancel = text("button", p.cancelling ? "Cancelling…" : "Cancel", {
      type: "button", class: "small", "data-testid": "process-cancel",
      title: "Stop this process job: on Slurm at once (scancel), a local step at its end",
    });
    cancel.disabled = !!p.cancelling;
    cancel.addEventListener("click", async () => {
      try {
        r.processing = await api("POST", `/runs/${encodeURIComponent(r.id)}/process/cancel`);
        r.processEvent = null;
        renderHistory();
      } catch (e) {
        showMessage(`cancel processing of ${r.id}: ${errText(e)}`);
      }
    });
    td.append(" ", cancel);
    return td;
  }
  if (p && p.state === "done") {
    const summary = r.processing ? r.processing.steps.map((s) => `${s.step}: ${s.summary || ""}`).join("\n") : "";
    td.append(text("span", "processed", { class: "state state-completed", title: summary }));
    return td;
  }
  const ended = !r.active && ["completed", "aborted", "failed"].includes(r.state) && r.steps_done > 0;
  if (!ended) return td;
  if (p && p.state === "failed") {
    td.append(text("span", "failed", { class: "state state-failed", title: p.error || "" }), " ");
  } else if (r.processed) {
    // Processed outside the daemon (`rigd process`).
    td.append(text("span", "processed", { class: "state state-completed", title: "by rigd process" }), " ");
  }
  const label = p && p.state === "failed" ? "Retry" : r.processed ? "Process again" : "Process";
  const b = text("button", label, {
    type: "button", class: "small", "data-testid": "process",
    title: "Rectify and compress this run (or photometric stereo, or the MDF, as the run calls for) in the daemon",
  });
  b.addEventListener("click", async () => {
    b.disabled = true;
    try {
      const job = await api("POST", `/runs/${encodeURIComponent(r.id)}/process`, {});
      r.processing = job;
      r.processEvent = null;
      renderHistory();
    } catch (e) {
      showMessage(`process ${r.id}: ${errText(e)}`);
      b.disabled = false;
    }
  });
  td.append(b);
  return td;
}

function onProcessEvent(runId, e) {
  const r = state.runs.find((x) => x.id === runId);
  if (!r) return;
  r.processEvent = e;
  // The end brings the result (and the viewer link) with the run's view.
  if (e.state === "done" || e.state === "failed") {
    r.processEvent = null;
    loadRun(runId);
  } else renderHistorySoon();
}

// --------------------------------------------------------------- log

function log(kind, msg, id) {
  const ol = $("log");
  const li = text("li", null, { "data-kind": kind });
  li.append(text("time", new Date().toLocaleTimeString()), text("span", kind, { class: "kind" }), text("span", msg));
  if (id != null) li.title = `event ${id}`;
  ol.prepend(li);
  while (ol.children.length > 200) ol.lastChild.remove();
}

function describe(ev) {
  const e = ev.event || {};
  switch (ev.kind) {
    case "engine":
      switch (e.type) {
        case "state":
          return `${ev.run}: ${e.from} → ${e.to}${e.reason ? ` (${e.reason})` : ""}`;
        case "step":
          return `${ev.run}: frame ${e.frames_done}/${e.frames_total} (images ${(e.images || []).join(", ")})`;
        case "retry":
          return `${ev.run}: retry ${e.device} (attempt ${e.attempt}): ${e.reason}`;
        case "refused":
          return `${ev.run}: refused ${e.command} in state ${e.state}`;
        default:
          return `${ev.run}: ${e.type}`;
      }
    case "run_created":
    case "run_resumed":
    case "run_ended":
      return `${ev.run}: ${e.state}${e.reason ? ` (${e.reason})` : ""}`;
    case "queue_changed":
      return `${(e.items || []).length} queued`;
    case "process":
      return `${ev.run}: processing ${e.state}${e.step ? `, ${e.step}${e.total ? ` ${e.done}/${e.total}` : ""}` : ""}${e.detail ? ` (${e.detail})` : ""}${e.error ? `: ${e.error}` : ""}`;
    case "tradeoff":
      return `trade-off report: ${e.state}${e.step ? ` (${e.step})` : ""}${e.error ? `: ${e.error}` : ""}`;
    case "estop":
      return `EMERGENCY STOP: ${e.all_stopped ? "all devices stopped" : "NOT all devices stopped"}${e.latency_s != null ? ` in ${e.latency_s.toFixed(3)} s` : ""}`;
    default:
      return JSON.stringify(e).slice(0, 200);
  }
}

// ---------------------------------------------------------------- SSE

function onEvent(ev) {
  const e = ev.event || {};
  const logKind = ev.kind === "engine" ? e.type : ev.kind;
  log(logKind, describe(ev), ev.id);
  switch (ev.kind) {
    case "engine":
      if (e.type === "step") onStep(ev.run, e);
      else if (e.type === "state") {
        const r = state.runs.find((x) => x.id === ev.run);
        if (r) {
          r.state = e.to;
          if (e.reason) r.reason = e.reason;
          if (r.id === state.shownId) renderRun();
          renderHistory();
        }
        loadRun(ev.run);
        refreshRig();
      }
      break;
    case "run_created":
    case "run_resumed":
      state.activeId = ev.run;
      if (state.shownId !== ev.run) {
        state.shownId = ev.run;
        state.stepsRun = null;
        state.steps = [];
        state.current = null;
        state.done = new Set();
      }
      upsertRun(e);
      loadSteps();
      refreshRig();
      break;
    case "run_ended":
      upsertRun(e);
      if (ev.run === state.shownId) loadSteps();
      loadRig();
      loadRuns();
      break;
    case "queue_changed":
      state.queue = e.items || [];
      renderQueue();
      break;
    case "tradeoff":
      onTradeoffEvent(e);
      break;
    case "process":
      onProcessEvent(ev.run, e);
      break;
    case "estop":
      showMessage(describe(ev), e.all_stopped ? "info" : "error");
      refreshRig();
      refreshShownRun();
      break;
    default:
      break;
  }
}

function onStep(runId, e) {
  if (runId !== state.shownId) {
    state.shownId = runId;
    state.stepsRun = null;
    loadRuns();
    return;
  }
  const r = shownRun();
  if (r) {
    r.steps_done = e.frames_done;
    r.steps_total = e.frames_total;
  }
  if (state.stepsRun === runId) {
    for (const i of e.images || []) state.done.add(i);
    const last = (e.images || [])[e.images.length - 1];
    const at = state.steps[last];
    const cur = at && at.index === last ? at : state.steps.find((s) => s.index === last);
    if (cur) state.current = cur;
    drawHemisphereSoon();
    refreshPreview();
  }
  renderRun();
  renderHistorySoon();
  refreshShownRun();
  refreshRig();
}

// The stream is reopened by hand rather than by EventSource's own retry:
// that retry sends Last-Event-ID, and after a daemon restart (ids start
// again from 1) the daemon would hold back every new event up to that id.
// A fresh stream plus a refetch of the whole state loses nothing but the
// missed events' log lines.
let stream = null;
let everOpen = false;
let retryMs = 500;

function setConn(st, label) {
  const conn = $("conn");
  conn.dataset.state = st;
  conn.textContent = label;
}

function connect() {
  const es = new EventSource(`${API}/events`);
  stream = es;
  es.onopen = () => {
    retryMs = 500;
    setConn("live", "live");
    log("info", everOpen ? "event stream reconnected; state refetched" : "event stream connected");
    everOpen = true;
    loadAll();
  };
  es.onerror = () => {
    if (stream !== es) return;
    es.close();
    stream = null;
    if (retryMs >= 4000) setConn("offline", "offline, retrying…");
    else setConn("reconnecting", "reconnecting…");
    setTimeout(connect, retryMs);
    retryMs = Math.min(retryMs * 2, 5000);
  };
  es.onmessage = (m) => {
    let ev;
    try {
      ev = JSON.parse(m.data);
    } catch (_) {
      return;
    }
    onEvent(ev);
  };
  es.addEventListener("lagged", () => {
    log("lagged", "missed events; refetching state");
    loadAll();
  });
}

window.addEventListener("offline", () => setConn("offline", "offline"));

// ------------------------------------------------------------ actions

function runRequest() {
  const sample = $("sample").value.trim();
  if (!sample) throw new Error("Enter a sample name.");
  const planSel = $("plan").value;
  let plan = planSel;
  if (planSel === "__custom") {
    const dirs = [];
    const lines = $("custom-dirs").value.split(/\n/).map((l) => l.trim()).filter(Boolean);
    for (const l of lines) {
      const parts = l.split(/[\s,;]+/).map(Number);
      if (parts.length !== 2 || parts.some((x) => !isFinite(x))) throw new Error(`Directions: “${l}” is not “θ φ”.`);
      dirs.push({ theta_deg: parts[0], phi_deg: parts[1] });
    }
    if (!dirs.length) throw new Error("Directions: enter at least one “θ φ” line.");
    plan = { directions: dirs };
  }
  const req = { sample, plan };
  const op = $("operator").value.trim();
  if (op) req.operator = op;
  const notes = $("notes").value.trim();
  if (notes) req.notes = notes;
  const exp = $("exposure").value.trim();
  if (exp) req.exposure_s = Number(exp);
  const policy = $("exposure-policy").value;
  if (policy) req.exposure_policy = JSON.parse(policy);
  const w = $("frame-w").value.trim();
  const h = $("frame-h").value.trim();
  if (w || h) {
    if (!w || !h) throw new Error("Give both frame width and height, or neither.");
    req.frame_size = [Number(w), Number(h)];
  }
  return req;
}

async function submitRun(queue) {
  const errBox = $("form-error");
  errBox.hidden = true;
  let req;
  try {
    req = runRequest();
  } catch (e) {
    errBox.textContent = e.message;
    errBox.hidden = false;
    return;
  }
  const btn = queue ? $("queue-add") : $("start");
  btn.disabled = true;
  try {
    if (queue) {
      const r = await api("POST", "/queue", req);
      showMessage(r.started_run ? `Queued and started ${r.started_run.id}` : `Queued ${req.sample}`, "info");
      await loadQueue();
    } else {
      const run = await api("POST", "/runs", req);
      showMessage(`Started ${run.id}`, "info");
    }
    await loadRuns();
  } catch (e) {
    errBox.textContent = errText(e);
    errBox.hidden = false;
  } finally {
    btn.disabled = false;
  }
}

async function command(cmd) {
  const id = state.shownId;
  if (!id) return;
  if (cmd === "abort" && !confirm(`Abort run ${id}? Its frames so far are kept; it cannot be resumed.`)) return;
  let query = "";
  if (cmd === "resume") {
    // No homing can restore the zero of an axis without homing: the
    // operator confirms it stands at its 0° mark.
    const unhomed = ((state.rig && state.rig.devices) || []).filter((d) => d.homing === false).map((d) => d.name);
    if (unhomed.length) {
      if (!confirm(`${unhomed.join(", ")} ${unhomed.length === 1 ? "has" : "have"} no homing. ` +
        "Is each at its 0° mark, with its controller zeroed there? Resume only if so.")) return;
      query = "?reference_confirmed=true";
    }
  }
  try {
    await api("POST", `/runs/${encodeURIComponent(id)}/${cmd}${query}`);
    log("info", `${cmd} sent to ${id}`);
    await loadRun(id);
  } catch (e) {
    showMessage(`${cmd}: ${errText(e)}`);
  }
}

// GET /rig/check: one line per device, usable or what is wrong and the fix.
async function checkRig() {
  const button = $("rig-check");
  const summary = $("rig-check-summary");
  const list = $("rig-check-list");
  button.disabled = true;
  summary.className = "";
  summary.textContent = "Checking every device…";
  list.replaceChildren();
  try {
    const r = await api("GET", "/rig/check");
    const bad = r.devices.filter((d) => !d.usable).length;
    summary.textContent = bad === 0
      ? `${r.profile}: all ${r.devices.length} devices usable`
      : `${r.profile}: ${bad} of ${r.devices.length} devices not usable`;
    summary.className = bad === 0 ? "ok-text" : "fault-text";
    for (const d of r.devices) {
      const li = text("li", "", { "data-device": d.device, class: d.usable ? "ok" : "fault" });
      li.append(text("strong", `${d.usable ? "OK" : "FAIL"} ${d.device}`), text("span", ` (${d.kind}): ${d.detail}`),
        text("span", ` (${d.connect_s.toFixed(2)} s)`, { class: "muted" }));
      if (d.fix) li.append(text("div", `Fix: ${d.fix}`, { class: "fault-text" }));
      list.append(li);
    }
  } catch (e) {
    summary.className = "fault-text";
    summary.textContent = `Rig check: ${errText(e)}`;
  } finally {
    button.disabled = false;
  }
}

// ---------------------------------------------------------- manual control

// Fills the manual-control selects from the rig's devices (once).
function fillManualSelects(rig) {
  const fill = (id, kinds) => {
    const sel = $(id);
    if (sel.options.length) return;
    for (const d of rig.devices.filter((d) => kinds.includes(d.kind))) {
      sel.append(text("option", d.name, { value: d.name }));
    }
  };
  fill("manual-axis", ["axis", "arm"]);
  fill("manual-lamp", ["lamp", "laser"]);
  fill("manual-camera", ["camera"]);
}

function manualStatus(msg, ok) {
  const st = $("manual-status");
  st.textContent = msg;
  st.className = ok ? "ok-text" : "fault-text";
}

function parseDir(id) {
  const parts = $(id).value.split(",").map((x) => Number(x.trim()));
  if (parts.length !== 2 || parts.some((x) => !Number.isFinite(x))) return null;
  return { theta_deg: parts[0], phi_deg: parts[1] };
}

// One manual action: POST, then say what happened (the daemon's words on error).
async function manual(path, body, describe) {
  manualStatus("…", true);
  try {
    const r = await api("POST", `/rig/manual/${path}`, body);
    manualStatus(describe(r), true);
    refreshRig();
    return r;
  } catch (e) {
    manualStatus(`${path}: ${errText(e)}`, false);
    return null;
  }
}

const degs = (r) => r.position_deg.map((x) => `${x.toFixed(2)}°`).join(", ");

function jog(sign) {
  const device = $("manual-axis").value;
  const step = Number($("manual-step").value);
  manual("jog", { device, by_deg: sign * step }, (r) => `${r.device} at ${degs(r)}`);
}

async function testFrame() {
  const r = await manual("frame", { camera: $("manual-camera").value || undefined }, (f) =>
    `test frame from ${f.camera}: ${f.width}×${f.height}, ${f.bit_depth}-bit, min ${f.min}, max ${f.max}, mean ${f.mean.toFixed(1)}, ${(100 * f.saturated).toFixed(1)} % saturated`);
  if (!r) return;
  state.testFrame = true;
  const img = $("preview");
  img.src = `${API}/rig/manual/frame?t=${Date.now()}`;
  img.alt = `Test frame from ${r.camera}`;
  $("preview-caption").textContent = `test frame from ${r.camera} (manual control)`;
}

// POST /rig/manual/holder-check: a test frame at the last pose, with the
// holder found in it: markers, registration, patches, each problem.
async function checkHolder() {
  const button = $("manual-holder");
  const out = $("manual-holder-result");
  button.disabled = true;
  // An old result must not stand beside a new failure.
  out.replaceChildren();
  out.hidden = true;
  const r = await manual("holder-check", { camera: $("manual-camera").value || undefined }, (c) =>
    `holder check from ${c.camera}: ${c.ok ? "OK" : `${c.problems.length} problem${c.problems.length === 1 ? "" : "s"}`}`);
  button.disabled = false;
  if (!r) return;
  renderHolderCheck(r);
  state.testFrame = true;
  const img = $("preview");
  img.src = `${API}/rig/manual/frame?t=${Date.now()}`;
  img.alt = `Holder check frame from ${r.camera}`;
  $("preview-caption").textContent = `holder check frame from ${r.camera} (manual control)`;
}

function renderHolderCheck(c) {
  const out = $("manual-holder-result");
  const px = (v) => (v == null ? "–" : `${v.toFixed(3)} px`);
  const summary = text("p", null, { "data-testid": "holder-summary", class: c.ok ? "ok-text" : "fault-text" });
  summary.textContent = `holder ${c.holder} (${c.profile}), ${c.camera} at view θ ${c.view.theta_deg.toFixed(1)}° ` +
    `φ ${c.view.phi_deg.toFixed(1)}°: ${c.markers_found} of ${c.markers.length} markers found, ` +
    `${c.registered ? "registered" : "not registered"}` +
    (c.registered ? `, residual RMS ${px(c.rms_px)}, max ${px(c.max_px)}` : "");
  out.append(summary);
  const areas = c.patches.concat(c.whites);
  if (areas.length) {
    const table = text("table", null, { class: "table", "data-testid": "holder-patches" });
    const head = table.createTHead().insertRow();
    for (const h of ["Patch", `Mean (${c.channels === 1 ? "grey" : "R G B"})`, "Clipped"]) {
      head.append(text("th", h, { scope: "col" }));
    }
    const body = table.createTBody();
    for (const a of areas) {
      const tr = body.insertRow();
      tr.dataset.patch = a.name;
      if (a.clipped.length) tr.className = "fault";
      tr.append(text("td", a.name), text("td", a.mean.map((v) => v.toFixed(4)).join(" ")),
        text("td", a.clipped.length ? a.clipped.join(", ") : "no"));
    }
    out.append(table);
  } else if (c.registered) {
    out.append(text("p", "This holder has no colour patches or white areas to read.", { class: "muted small" }));
  }
  const list = text("ul", null, { class: "check-list", "data-testid": "holder-problems" });
  if (c.ok) {
    const li = text("li", "", { class: "ok" });
    li.append(text("strong", "OK"), text("span", " every marker found, nothing clipped"));
    list.append(li);
  }
  for (const p of c.problems) {
    const li = text("li", "", { class: "fault" });
    li.append(text("strong", "FAIL"), text("span", ` ${p}`));
    list.append(li);
  }
  out.append(list);
  out.hidden = false;
}

function setupManual() {
  $("manual-home").addEventListener("click", () => {
    const device = $("manual-axis").value;
    manual("home", { device }, (r) => `${r.device} homed at ${degs(r)}`);
  });
  $("manual-minus").addEventListener("click", () => jog(-1));
  $("manual-plus").addEventListener("click", () => jog(1));
  $("manual-goto").addEventListener("click", () => {
    const device = $("manual-axis").value;
    manual("jog", { device, to_deg: Number($("manual-to").value) }, (r) => `${r.device} at ${degs(r)}`);
  });
  $("manual-pose").addEventListener("click", () => {
    const light = parseDir("manual-light");
    const view = parseDir("manual-view");
    if (!light || !view) {
      manualStatus("pose: give each direction as θ,φ in degrees", false);
      return;
    }
    manual("pose", { light, view }, (r) =>
      `pose reached: ${Object.entries(r.axes).map(([n, x]) => `${n} ${x.toFixed(2)}°`).join(", ")}` +
      `${r.arm ? `, arm ${r.arm.map((x) => x.toFixed(1)).join("/")}°` : ""}; lit by ${r.lamp}, seen by ${r.camera}` +
      `${r.feasible ? "" : ` (substitute: ${r.reason})`}`);
  });
  const sw = (on) => manual("lamp", { device: $("manual-lamp").value, on }, (r) => `${r.device} ${r.on ? "ON" : "off"}`);
  $("manual-on").addEventListener("click", () => sw(true));
  $("manual-off").addEventListener("click", () => sw(false));
  $("manual-frame").addEventListener("click", testFrame);
  $("manual-holder").addEventListener("click", checkHolder);
}

async function estop() {
  try {
    const r = await api("POST", "/estop");
    showMessage(
      r.run ? `EMERGENCY STOP: run ${r.run} paused; ${r.all_stopped ? "all devices stopped" : "NOT all devices stopped"}` : "EMERGENCY STOP sent (no active run)",
      r.all_stopped || !r.run ? "info" : "error",
    );
    loadAll();
  } catch (e) {
    showMessage(`EMERGENCY STOP FAILED: ${errText(e)}`);
  }
}

// -------------------------------------------------------------- setup

function setup() {
  setupTokenDialog();
  $("run-form").addEventListener("submit", (e) => {
    e.preventDefault();
    submitRun(false);
  });
  $("queue-add").addEventListener("click", () => submitRun(true));
  $("plan").addEventListener("change", () => {
    state.planChosen = true;
    planChanged();
  });
  $("exposure-policy").addEventListener("change", planChanged);
  $("pause").addEventListener("click", () => command("pause"));
  $("resume").addEventListener("click", () => command("resume"));
  $("abort").addEventListener("click", () => command("abort"));
  $("estop").addEventListener("click", estop);
  $("rig-check").addEventListener("click", checkRig);
  setupManual();
  $("tradeoff-start").addEventListener("click", startTradeoff);
  setupHistory();
  drawHemisphere();
  connect();
  if (!token()) askToken("No API token is stored in this browser yet.");
  document.body.dataset.ready = "true";
}

setup();
