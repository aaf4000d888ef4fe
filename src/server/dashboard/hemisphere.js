// Hemisphere plots: polar plots (θ radial 0–90°, φ counter-clockwise from
// the right) of a run's light and view directions, drawn as plain SVG.

const SVG = "http://www.w3.org/2000/svg";
const SIZE = 240;
const C = SIZE / 2;
const R = SIZE / 2 - 22;

function el(name, attrs = {}, parent = null) {
  const e = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  if (parent) parent.appendChild(e);
  return e;
}

function xy(dir) {
  const r = (Math.max(0, Math.min(90, dir.theta_deg)) / 90) * R;
  const a = (dir.phi_deg * Math.PI) / 180;
  return [C + r * Math.cos(a), C - r * Math.sin(a)];
}

function key(dir) {
  return `${dir.theta_deg.toFixed(1)}/${(((dir.phi_deg % 360) + 360) % 360).toFixed(1)}`;
}

/** Groups a run's steps by unique light and view direction. */
export function summarize(steps, doneSet) {
  const groups = { lights: new Map(), views: new Map() };
  for (const s of steps) {
    const done = doneSet.has(s.index);
    for (const [which, dir] of [["lights", s.light], ["views", s.view]]) {
      const k = key(dir);
      let g = groups[which].get(k);
      if (!g) {
        g = { dir, total: 0, done: 0, feasible: 0, indices: [] };
        groups[which].set(k, g);
      }
      g.total += 1;
      if (done) g.done += 1;
      if (s.feasible) g.feasible += 1;
      g.indices.push(s.index);
    }
  }
  return groups;
}

/**
 * Draws one polar plot into `container`.
 * which: "lights" | "views"; steps: the run's steps; doneSet: indices done;
 * current: the step last captured (or null).
 */
export function drawPlot(container, which, steps, doneSet, current) {
  const groups = summarize(steps, doneSet)[which];
  const svg = el("svg", {
    viewBox: `0 0 ${SIZE} ${SIZE}`,
    class: `polar ${which}`,
    role: "img",
    "data-testid": `hemi-${which}`,
  });
  const title = el("title", {}, svg);
  let done = 0;
  let partial = 0;
  for (const g of groups.values()) {
    if (g.done === g.total) done += 1;
    else if (g.done > 0) partial += 1;
  }
  title.textContent = `${which}: ${groups.size} directions, ${done} captured, ${partial} partly captured`;

  // Grid: θ = 30, 60, 90 circles; φ spokes every 45°.
  const grid = el("g", { class: "grid" }, svg);
  for (const t of [90, 60, 30]) {
    el("circle", { cx: C, cy: C, r: (t / 90) * R, class: t === 90 ? "rim" : "ring" }, grid);
  }
  for (const t of [30, 60]) {
    // θ labels along the φ = 112.5° direction, clear of the spokes.
    const [lx, ly] = xy({ theta_deg: t, phi_deg: 112.5 });
    const lab = el("text", { x: lx, y: ly + 3, class: "tick theta", "text-anchor": "middle" }, grid);
    lab.textContent = `${t}°`;
  }
  for (let p = 0; p < 360; p += 45) {
    const [x, y] = xy({ theta_deg: 90, phi_deg: p });
    el("line", { x1: C, y1: C, x2: x, y2: y, class: "spoke" }, grid);
    if (p % 90 === 0) {
      const [lx, ly] = xy({ theta_deg: 90 + 12, phi_deg: p });
      const t = el("text", { x: lx, y: ly + 4, class: "tick", "text-anchor": "middle" }, grid);
      t.textContent = `${p}°`;
    }
  }
  const heading = el("text", { x: 4, y: 12, class: "plot-title" }, svg);
  heading.textContent = which === "lights" ? "Lights" : "Views";

  const n = groups.size;
  const rad = n > 60 ? 3.2 : n > 20 ? 4.5 : 6;
  const marks = el("g", { class: "marks" }, svg);
  for (const g of groups.values()) {
    const [x, y] = xy(g.dir);
    const state =
      g.feasible === 0 && g.done === 0
        ? "infeasible"
        : g.done === g.total
          ? "done"
          : g.done > 0
            ? "partial"
            : "todo";
    const m = el("g", {
      class: `mk mk-${state}`,
      "data-testid": "hemi-marker",
      "data-state": state,
      "data-which": which,
    }, marks);
    const t = el("title", {}, m);
    t.textContent = `θ ${g.dir.theta_deg.toFixed(1)}°, φ ${g.dir.phi_deg.toFixed(1)}°: ${g.done}/${g.total} captured${g.feasible < g.total ? `, ${g.total - g.feasible} infeasible` : ""}`;
    if (state === "infeasible") {
      el("path", { d: cross(x, y, rad), class: "cross" }, m);
    } else {
      el("circle", { cx: x, cy: y, r: rad, class: `${which}` }, m);
    }
  }
  // Infeasible steps: a cross where the view actually was (views plot).
  if (which === "views") {
    const crosses = el("g", { class: "crosses" }, svg);
    const seen = new Set();
    for (const s of steps) {
      if (s.feasible) continue;
      const k = key(s.achieved_view);
      if (seen.has(k)) continue;
      seen.add(k);
      const [x, y] = xy(s.achieved_view);
      const c = el("path", { d: cross(x, y, rad * 0.8), class: "cross", "data-testid": "hemi-infeasible" }, crosses);
      const t = el("title", {}, c);
      t.textContent = s.reason || "infeasible";
    }
  }
  if (current) {
    const dir = which === "lights" ? current.light : current.view;
    const [x, y] = xy(dir);
    el("circle", { cx: x, cy: y, r: rad + 4, class: "current-ring", "data-testid": "hemi-current" }, svg);
  }
  container.replaceChildren(svg);
}

function cross(x, y, r) {
  return `M${x - r} ${y - r}L${x + r} ${y + r}M${x + r} ${y - r}L${x - r} ${y + r}`;
}
