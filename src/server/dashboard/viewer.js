// rigd BTF viewer: relights a processed run on a mesh with WebGL2.
// The image is computed exactly as `rigd process render` computes it on
// the CPU (crates/process/src/relight.rs documents each step); the browser test
// compares the two. Left half: the BTF; right half: a plain texture.
//
// URL parameters (all optional): mesh=flat|cylinder|cloth, light=θ,φ,
// view=θ,φ, size=N (pixels per half), exposure=X, mode=point|env,
// components=C (fewer PCA components for a GPU with less room).
// window.rigdViewer exposes the state for tests and scripts.

const $ = (id) => document.getElementById(id);
const run = decodeURIComponent(location.pathname.split("/").filter(Boolean).pop() || "");
const params = new URLSearchParams(location.search);

// Constants shared with crates/process/src/relight.rs.
const CAMERA_DISTANCE = 4.5, FOV_DEG = 40, NEAR = 0.1, FAR = 20;
const BACKGROUND = 0.12, SHADOW_SOFTNESS = 0.05, DISPLAY_GAMMA = 2.2;
const MAX_ENTRIES = 64; // interpolation entries per table in the shader

function parsePair(s, fallback) {
  if (!s) return fallback;
  const p = s.split(",").map(Number);
  return p.length === 2 && p.every(Number.isFinite) ? p : fallback;
}

const state = {
  mesh: params.get("mesh") || "flat",
  mode: params.get("mode") || "point",
  light: parsePair(params.get("light"), [30, 45]),
  view: parsePair(params.get("view"), [35, 270]),
  exposure: Number(params.get("exposure") || 1),
  alphaDeg: 0,
  size: Math.max(64, Math.min(1024, Number(params.get("size") || 512))),
};

const viewer = {
  ready: false, error: null, frames: 0, kind: null,
  state,
  setLight(theta, phi) { state.light = [theta, wrap(phi)]; draw(); },
  setView(theta, phi) { state.view = [clamp(theta, 0, 89), wrap(phi)]; draw(); },
  async setMesh(name) { state.mesh = name; $("mesh").value = name; await loadMesh(); draw(); },
  async setMode(mode) { state.mode = mode; $("mode").value = mode; if (mode === "env") updateEnv(); draw(); },
  pixels: readLeftHalf,
  benchmark,
};
window.rigdViewer = viewer;

function clamp(x, lo, hi) { return Math.min(hi, Math.max(lo, x)); }
function wrap(phi) { return ((phi % 360) + 360) % 360; }
function showError(msg) {
  viewer.error = msg;
  const m = $("message");
  m.textContent = msg;
  m.hidden = false;
  $("status").textContent = "error";
}
const rad = (d) => (d * Math.PI) / 180;
function unitOf([theta, phi]) {
  const t = rad(theta), p = rad(phi);
  return [Math.sin(t) * Math.cos(p), Math.sin(t) * Math.sin(p), Math.cos(t)];
}
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];

// The orbit camera of render.rs: column-major view-projection for GL.
function camera([theta, phi]) {
  const st = Math.sin(rad(theta)), ct = Math.cos(rad(theta));
  const sp = Math.sin(rad(phi)), cp = Math.cos(rad(phi));
  const back = [st * cp, st * sp, ct], right = [-sp, cp, 0], up = [-ct * cp, -ct * sp, st];
  const eye = back.map((c) => c * CAMERA_DISTANCE);
  const view = [
    [...right, -dot(right, eye)],
    [...up, -dot(up, eye)],
    [...back, -dot(back, eye)],
    [0, 0, 0, 1],
  ];
  const f = 1 / Math.tan(rad(FOV_DEG) / 2);
  const proj = [
    [f, 0, 0, 0],
    [0, f, 0, 0],
    [0, 0, (FAR + NEAR) / (NEAR - FAR), (2 * FAR * NEAR) / (NEAR - FAR)],
    [0, 0, -1, 0],
  ];
  const m = new Float32Array(16);
  for (let r = 0; r < 4; r++)
    for (let c = 0; c < 4; c++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += proj[r][k] * view[k][c];
      m[c * 4 + r] = s;
    }
  return { eye, vp: m };
}

const VERTEX = `#version 300 es
in vec3 aPos; in vec3 aNormal; in vec3 aTangent; in vec2 aTex; in vec2 aParam;
uniform mat4 uVP; uniform vec3 uLight; uniform float uAlpha;
out vec3 vP; out vec3 vN; out vec3 vT; out vec2 vTex; out vec2 vParam; out float vU;
void main() {
  vP = aPos; vN = aNormal; vT = aTangent; vTex = aTex; vParam = aParam;
  float angle = acos(clamp(dot(aNormal, uLight), -1.0, 1.0));
  vU = (1.0 + cos(uAlpha + angle)) * 0.5;   // Sattler et al. eq. 6
  gl_Position = uVP * vec4(aPos, 1.0);
}`;

// Eq. 3 / eq. 5 interpolation over a ring table, as
// crates/process/src/directions.rs does it. Tables live in uTables (RGBA32F):
// row 2T holds rings (θ, first member, count, pole), row 2T+1 members
// (φ, direction index). Entries go to e{L,V}_i / e{L,V}_w.
const INTERP = (T, row) => `
int e${T}_n; int e${T}_i[${MAX_ENTRIES}]; float e${T}_w[${MAX_ENTRIES}];
void push${T}(int index, float w) {
  if (e${T}_n < ${MAX_ENTRIES}) { e${T}_i[e${T}_n] = index; e${T}_w[e${T}_n] = w; e${T}_n++; }
}
vec2 member${T}(int k) { return texelFetch(uTables, ivec2(k, ${row + 1}), 0).xy; }
void uniform${T}(vec4 ring, float scale) {
  int start = int(ring.y), n = int(ring.z);
  for (int k = 0; k < n; k++) push${T}(int(member${T}(start + k).y), scale / float(n));
}
void ring${T}(int r, float phi, float scale) {
  vec4 ring = texelFetch(uTables, ivec2(r, ${row}), 0);
  int start = int(ring.y), n = int(ring.z);
  if (ring.w > 0.5) { uniform${T}(ring, scale); return; }
  if (n == 1) { push${T}(int(member${T}(start).y), scale); return; }
  int after = n;
  for (int k = 0; k < n; k++) { if (member${T}(start + k).x > phi) { after = k; break; } }
  int lo = after == 0 ? n - 1 : after - 1;
  int hi = (lo + 1) % n;
  vec2 a = member${T}(start + lo), b = member${T}(start + hi);
  float gap = mod(b.x - a.x, 360.0);
  if (gap <= 0.0) { push${T}(int(a.y), scale); return; }
  float s = clamp(mod(phi - a.x, 360.0) / gap, 0.0, 1.0);
  push${T}(int(a.y), scale * (1.0 - s));
  push${T}(int(b.y), scale * s);
}
void interpolate${T}(vec3 local, int rings) {
  e${T}_n = 0;
  float theta = clamp(degrees(acos(clamp(local.z, -1.0, 1.0))), 0.0, 90.0);
  float phi = abs(local.x) + abs(local.y) > 0.0 ? degrees(atan(local.y, local.x)) : 0.0;
  phi = mod(phi, 360.0);
  if (phi >= 360.0) phi = 0.0;
  vec4 first = texelFetch(uTables, ivec2(0, ${row}), 0);
  vec4 last = texelFetch(uTables, ivec2(rings - 1, ${row}), 0);
  if (theta <= first.x) {
    if (first.w > 0.5 || first.x <= 0.0) { ring${T}(0, phi, 1.0); }
    else { float t = theta / first.x; ring${T}(0, phi, t); uniform${T}(first, 1.0 - t); }
  } else if (theta >= last.x) {
    ring${T}(rings - 1, phi, 1.0);
  } else {
    int upper = 1;
    for (int r = 1; r < rings; r++) { upper = r; if (texelFetch(uTables, ivec2(r, ${row}), 0).x > theta) break; }
    float below = texelFetch(uTables, ivec2(upper - 1, ${row}), 0).x;
    float above = texelFetch(uTables, ivec2(upper, ${row}), 0).x;
    float t = (theta - below) / (above - below);
    ring${T}(upper - 1, phi, 1.0 - t);
    ring${T}(upper, phi, t);
  }
}`;

const FRAGMENT = `#version 300 es
precision highp float; precision highp int; precision highp sampler2DArray;
in vec3 vP; in vec3 vN; in vec3 vT; in vec2 vTex; in vec2 vParam; in float vU;
uniform highp sampler2DArray uTex;   // layer slot*(C+1)+k; PS: 0 albedo, 1 normals
uniform highp sampler2D uWeights;    // (light*C + k, slot)
uniform highp sampler2D uTables;
uniform highp sampler2DArray uEnv;   // environment mode: g_i per grid vertex, layer i
uniform int uKind;       // 0 BTF, 1 photometric stereo
uniform int uShading;    // 0 as measured, 1 plain texture
uniform int uEnvMode;    // 1: environment light
uniform int uC; uniform int uChannels; uniform int uLights;
uniform int uLightRings; uniform int uViewRings;
uniform vec3 uLight; uniform vec3 uEye; uniform float uExposure;
uniform vec2 uGrid;      // nu, nv of the mesh
out vec4 outColor;
${INTERP("L", 0)}
${INTERP("V", 2)}
vec3 layer(int k) {
  vec4 c = texture(uTex, vec3(vTex.x, -vTex.y, float(k)));
  return uChannels == 1 ? c.rrr : c.rgb;
}
float weight(int slot, int light, int k) {
  return texelFetch(uWeights, ivec2(light * uC + k, slot), 0).r;
}
vec3 envG(int i) {
  vec2 at = (vParam * (uGrid - 1.0) + 0.5) / uGrid;
  return texture(uEnv, vec3(at, float(i))).rgb;
}
// Σ_s ω_s (M_s + Σ_k γ_sk B_sk), the light weights in eL.
vec3 btf() {
  vec3 value = vec3(0.0);
  for (int e = 0; e < eV_n; e++) {
    int slot = eV_i[e]; float omega = eV_w[e];
    int base = slot * (uC + 1);
    value += omega * layer(base);
    for (int k = 0; k < uC; k++) {
      float gamma = 0.0;
      for (int j = 0; j < eL_n; j++) gamma += eL_w[j] * weight(slot, eL_i[j], k);
      if (gamma != 0.0) value += omega * gamma * layer(base + 1 + k);
    }
  }
  return value;
}
// Sattler et al. eq. 10-11: every measured light weighted by the sky it sees.
vec3 btfEnvironment() {
  vec3 value = vec3(0.0);
  vec3 total = vec3(0.0);
  for (int i = 0; i < uLights; i++) total += envG(i);
  for (int e = 0; e < eV_n; e++) {
    int slot = eV_i[e]; float omega = eV_w[e];
    int base = slot * (uC + 1);
    value += omega * total * layer(base);
    for (int k = 0; k < uC; k++) {
      vec3 gamma = vec3(0.0);
      for (int i = 0; i < uLights; i++) gamma += envG(i) * weight(slot, i, k);
      value += omega * gamma * layer(base + 1 + k);
    }
  }
  return value;
}
void main() {
  vec3 n = normalize(vN);
  vec3 t = normalize(vT - n * dot(n, vT));
  vec3 b = cross(n, t);
  vec3 V = normalize(uEye - vP);
  vec3 l = vec3(dot(uLight, t), dot(uLight, b), dot(uLight, n));
  vec3 v = vec3(dot(V, t), dot(V, b), dot(V, n));
  float x = clamp((vU - 0.5) / ${SHADOW_SOFTNESS.toFixed(4)}, 0.0, 1.0);
  float shadow = x * x * (3.0 - 2.0 * x);
  vec3 value;
  if (uKind == 1) {
    vec3 albedo = texture(uTex, vec3(vTex.x, -vTex.y, 0.0)).rgb;
    vec3 m = texture(uTex, vec3(vTex.x, -vTex.y, 1.0)).rgb;
    vec3 bump = uShading == 0 ? normalize(t * m.x + b * m.y + n * m.z) : n;
    float diffuse = max(dot(bump, uLight), 0.0);
    float spec = uShading == 0 ? 0.25 * pow(max(dot(bump, normalize(uLight + V)), 0.0), 40.0) : 0.0;
    value = albedo * diffuse + vec3(spec);
  } else if (uEnvMode == 1) {
    if (uShading == 1) { interpolateV(vec3(0.0, 0.0, 1.0), uViewRings); } else { interpolateV(v, uViewRings); }
    value = btfEnvironment();
    shadow = 1.0;   // the visibility maps shadow instead
  } else if (uShading == 1) {
    interpolateV(vec3(0.0, 0.0, 1.0), uViewRings);
    interpolateL(vec3(0.0, 0.0, 1.0), uLightRings);
    value = btf() * max(l.z, 0.0);
  } else {
    interpolateV(v, uViewRings);
    interpolateL(l, uLightRings);
    value = btf();
  }
  vec3 linear = clamp(uExposure * shadow * value, 0.0, 1.0);
  outColor = vec4(pow(linear, vec3(1.0 / ${DISPLAY_GAMMA.toFixed(1)})), 1.0);
}`;

const canvas = $("canvas");
const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
let program = null, uniforms = {}, manifest = null, mesh = null, meshGl = null;
let textures = {};

function compile(type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s) || "shader");
  return s;
}

function buildProgram() {
  program = gl.createProgram();
  gl.attachShader(program, compile(gl.VERTEX_SHADER, VERTEX));
  gl.attachShader(program, compile(gl.FRAGMENT_SHADER, FRAGMENT));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program) || "link");
  const n = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const info = gl.getActiveUniform(program, i);
    uniforms[info.name.replace(/\[0\]$/, "")] = gl.getUniformLocation(program, info.name);
  }
}

function texture2d(unit, internal, format, type, w, h, data, filter) {
  const t = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D, t);
  gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  return t;
}

function textureArray(unit, internal, format, w, h, layers, data, wrapMode) {
  const t = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
  gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, w, h, layers, 0, format, gl.HALF_FLOAT, data);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, wrapMode);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, wrapMode);
  return t;
}

// Row 2T: rings (θ, first member, count, pole); row 2T+1: members (φ, index).
function tablesTexture(tables) {
  const rowsOf = (t) => {
    const rings = [], members = [];
    for (const r of t.rings) {
      rings.push([r.theta_deg, members.length, r.members.length, r.pole ? 1 : 0]);
      for (const [phi, index] of r.members) members.push([phi, index, 0, 0]);
    }
    return [rings, members];
  };
  const rows = tables.flatMap(rowsOf);
  const width = Math.max(...rows.map((r) => r.length));
  const data = new Float32Array(width * rows.length * 4);
  rows.forEach((row, y) => row.forEach((texel, x) => data.set(texel, (y * width + x) * 4)));
  return texture2d(2, gl.RGBA32F, gl.RGBA, gl.FLOAT, width, rows.length, data, gl.NEAREST);
}

async function fetchJson(url) {
  const r = await fetch(url);
  const body = await r.json().catch(() => null);
  if (!r.ok) throw new Error((body && body.detail) || `${url}: HTTP ${r.status}`);
  return body;
}

async function loadMaterial() {
  const comps = Number(params.get("components"));
  const query = Number.isInteger(comps) && comps > 0 ? `?components=${comps}` : "";
  manifest = await fetchJson(`/api/v1/runs/${encodeURIComponent(run)}/btf${query}`);
  if (manifest.version !== 1) throw new Error(`unknown pack version ${manifest.version}`);
  viewer.kind = manifest.kind;
  const r = await fetch(manifest.data_url);
  if (!r.ok) throw new Error(`material data: HTTP ${r.status}`);
  const blob = await r.arrayBuffer();
  const { width, height, layers } = manifest;
  const halfs = new Uint16Array(blob, manifest.textures.offset, manifest.textures.bytes / 2);
  const maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
  if (layers > maxLayers) throw new Error(`${layers} texture layers; this GPU holds ${maxLayers}: ask for fewer components (?components=)`);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  const grey = manifest.channels === 1;
  textures.tex = textureArray(0, grey ? gl.R16F : gl.RGB16F, grey ? gl.RED : gl.RGB, width, height, layers, halfs, gl.REPEAT);
  if (manifest.kind === "btf") {
    const c = Math.max(1, manifest.components), lights = manifest.light_table.directions.length;
    const slots = manifest.view_table.directions.length;
    for (const t of [manifest.light_table, manifest.view_table])
      for (const ring of t.rings)
        if (ring.members.length + 2 > MAX_ENTRIES) throw new Error(`a ring of ${ring.members.length} directions: the viewer takes at most ${MAX_ENTRIES - 2}`);
    const maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (lights * c > maxSize) throw new Error(`${lights} lights × ${c} components exceed this GPU's ${maxSize}-texel rows: ask for fewer components (?components=)`);
    const w = manifest.components > 0
      ? new Float32Array(blob, manifest.weights.offset, manifest.weights.bytes / 4)
      : new Float32Array(lights * slots);
    textures.weights = texture2d(1, gl.R32F, gl.RED, gl.FLOAT, lights * c, slots, w, gl.NEAREST);
    textures.tables = tablesTexture([manifest.light_table, manifest.view_table]);
  } else {
    $("mode").disabled = true;
    $("left-caption").textContent = "photometric stereo: albedo + normals (bump mapped)";
  }
}

async function loadMesh() {
  mesh = await fetchJson(`/api/v1/runs/${encodeURIComponent(run)}/btf/mesh/${state.mesh}`);
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const attr = (name, data, size) => {
    const loc = gl.getAttribLocation(program, name);
    if (loc < 0) return;
    const b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
  };
  attr("aPos", mesh.positions, 3);
  attr("aNormal", mesh.normals, 3);
  attr("aTangent", mesh.tangents, 3);
  attr("aTex", mesh.texcoords, 2);
  attr("aParam", mesh.params, 2);
  const ib = gl.createBuffer();
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
  gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, new Uint32Array(mesh.indices), gl.STATIC_DRAW);
  meshGl = { vao, count: mesh.indices.length };
  if (state.mode === "env") updateEnv();
}

// Environment light: a sky (zenith blue, bright horizon, dark ground) and
// a sun at the light's direction. Per vertex and measured light i:
// g_i = visible_i · sky(world direction of i) · solid angle_i (eq. 10).
function sky(d, sun) {
  if (d[2] <= 0) return [0.05, 0.045, 0.04];
  const s = Math.pow(Math.max(dot(d, sun), 0), 48) * 6;
  const z = d[2];
  return [0.55 - 0.3 * z + s, 0.62 - 0.2 * z + s, 0.75 + 0.1 * z + s * 0.9];
}

function updateEnv() {
  if (!mesh || !manifest || manifest.kind !== "btf") return;
  const dirs = manifest.light_table.directions.map((d) => unitOf([d.theta_deg, d.phi_deg]));
  const omega = manifest.light_table.solid_angle_sr;
  const lights = dirs.length, nverts = mesh.nu * mesh.nv;
  const sun = unitOf(state.light);
  const data = new Uint16Array(lights * nverts * 4);
  for (let v = 0; v < nverts; v++) {
    const n = mesh.normals.slice(3 * v, 3 * v + 3), t = mesh.tangents.slice(3 * v, 3 * v + 3);
    const b = cross(n, t);
    for (let i = 0; i < lights; i++) {
      const d = dirs[i];
      const w = [0, 1, 2].map((c) => t[c] * d[0] + b[c] * d[1] + n[c] * d[2]);
      const visible = mesh.visibility[v * mesh.visibility_directions + i];
      const g = visible ? sky(w, sun).map((c) => c * omega[i] / Math.PI) : [0, 0, 0];
      const at = (i * nverts + v) * 4;
      for (let c = 0; c < 3; c++) data[at + c] = toHalf(g[c]);
      data[at + 3] = toHalf(1);
    }
  }
  if (textures.env) gl.deleteTexture(textures.env);
  textures.env = textureArray(3, gl.RGBA16F, gl.RGBA, mesh.nu, mesh.nv, lights, data, gl.CLAMP_TO_EDGE);
}

const f32 = new Float32Array(1), u32 = new Uint32Array(f32.buffer);
function toHalf(x) {
  f32[0] = x;
  const b = u32[0], sign = (b >>> 16) & 0x8000, e = ((b >>> 23) & 0xff) - 127 + 15, m = b & 0x7fffff;
  if (e <= 0) return sign;
  if (e >= 31) return sign | 0x7c00;
  return sign | ((e << 10) + ((m + 0x1000) >>> 13)); // a rounding carry may bump the exponent
}

function setUniforms(shading) {
  const cam = camera(state.view);
  const L = unitOf(state.light);
  gl.uniformMatrix4fv(uniforms.uVP, false, cam.vp);
  gl.uniform3fv(uniforms.uLight, L);
  gl.uniform3fv(uniforms.uEye, cam.eye);
  gl.uniform1f(uniforms.uExposure, state.exposure);
  gl.uniform1f(uniforms.uAlpha, rad(state.alphaDeg));
  gl.uniform1i(uniforms.uShading, shading);
  gl.uniform1i(uniforms.uKind, manifest.kind === "btf" ? 0 : 1);
  gl.uniform1i(uniforms.uEnvMode, state.mode === "env" && manifest.kind === "btf" ? 1 : 0);
  gl.uniform1i(uniforms.uC, manifest.components);
  gl.uniform1i(uniforms.uChannels, manifest.channels);
  if (manifest.kind === "btf") {
    gl.uniform1i(uniforms.uLights, manifest.light_table.directions.length);
    gl.uniform1i(uniforms.uLightRings, manifest.light_table.rings.length);
    gl.uniform1i(uniforms.uViewRings, manifest.view_table.rings.length);
  }
  gl.uniform2f(uniforms.uGrid, mesh.nu, mesh.nv);
  for (const [name, unit] of [["uTex", 0], ["uWeights", 1], ["uTables", 2], ["uEnv", 3]])
    if (uniforms[name]) gl.uniform1i(uniforms[name], unit);
}

function renderFrame() {
  if (!program || !manifest || !meshGl) return;
  const s = state.size;
  gl.enable(gl.DEPTH_TEST);
  gl.depthFunc(gl.LESS);
  gl.disable(gl.CULL_FACE);
  gl.clearColor(BACKGROUND, BACKGROUND, BACKGROUND, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.useProgram(program);
  gl.bindVertexArray(meshGl.vao);
  for (const [x, shading] of [[0, 0], [s, 1]]) {
    gl.viewport(x, 0, s, s);
    setUniforms(shading);
    gl.drawElements(gl.TRIANGLES, meshGl.count, gl.UNSIGNED_INT, 0);
  }
  viewer.frames++;
  $("light-theta").textContent = state.light[0].toFixed(1);
  $("light-phi").textContent = state.light[1].toFixed(1);
  $("view-theta").textContent = state.view[0].toFixed(1);
  $("view-phi").textContent = state.view[1].toFixed(1);
  drawDisk();
}

let pending = false;
function draw() {
  if (pending) return;
  pending = true;
  requestAnimationFrame(() => { pending = false; renderFrame(); });
}

// The left half as RGB rows from the top (an array of 0-255 values): what
// the test compares with `rigd process render`.
function readLeftHalf() {
  renderFrame();
  const s = state.size;
  const rgba = new Uint8Array(s * s * 4);
  gl.readPixels(0, 0, s, s, gl.RGBA, gl.UNSIGNED_BYTE, rgba);
  const rgb = new Uint8Array(s * s * 3);
  for (let y = 0; y < s; y++)
    for (let x = 0; x < s; x++) {
      const from = ((s - 1 - y) * s + x) * 4, to = (y * s + x) * 3;
      rgb[to] = rgba[from]; rgb[to + 1] = rgba[from + 1]; rgb[to + 2] = rgba[from + 2];
    }
  return Array.from(rgb);
}

// Frames per second over `n` frames, each finished before the next.
function benchmark(n) {
  const t0 = performance.now();
  const px = new Uint8Array(4);
  for (let i = 0; i < n; i++) {
    renderFrame();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
  }
  return (1000 * n) / (performance.now() - t0);
}

// The light disk: centre overhead, the circle the horizon (θ = 90°),
// the ring outside it down to θ = 120° below the horizon.
const disk = $("light-disk");
const DISK_R = 60, DISK_MAX = 120;
function drawDisk() {
  const c = disk.getContext("2d");
  const cx = disk.width / 2, cy = disk.height / 2;
  c.clearRect(0, 0, disk.width, disk.height);
  c.fillStyle = "#333"; c.beginPath(); c.arc(cx, cy, (DISK_R * DISK_MAX) / 90, 0, 2 * Math.PI); c.fill();
  c.fillStyle = "#1b2733"; c.beginPath(); c.arc(cx, cy, DISK_R, 0, 2 * Math.PI); c.fill();
  c.strokeStyle = "#c5d0da"; c.stroke();
  const r = (DISK_R * state.light[0]) / 90, p = rad(state.light[1]);
  c.fillStyle = state.light[0] > 90 ? "#777" : "#ffcc33";
  c.beginPath(); c.arc(cx + r * Math.cos(p), cy - r * Math.sin(p), 6, 0, 2 * Math.PI); c.fill();
}
function diskPick(ev) {
  const box = disk.getBoundingClientRect();
  const x = ev.clientX - box.left - box.width / 2, y = box.height / 2 - (ev.clientY - box.top);
  const theta = Math.min(DISK_MAX, (Math.hypot(x, y) / DISK_R) * 90);
  viewer.setLight(theta, (Math.atan2(y, x) * 180) / Math.PI);
  if (state.mode === "env") updateEnv();
}
disk.addEventListener("pointerdown", (ev) => { disk.setPointerCapture(ev.pointerId); diskPick(ev); });
disk.addEventListener("pointermove", (ev) => { if (ev.buttons) diskPick(ev); });

// Drag on the image: orbit the camera; with shift, move the light.
let drag = null;
canvas.addEventListener("pointerdown", (ev) => { canvas.setPointerCapture(ev.pointerId); drag = [ev.clientX, ev.clientY]; });
canvas.addEventListener("pointerup", () => { drag = null; });
canvas.addEventListener("pointermove", (ev) => {
  if (!drag || !ev.buttons) return;
  const dx = ev.clientX - drag[0], dy = ev.clientY - drag[1];
  drag = [ev.clientX, ev.clientY];
  if (ev.shiftKey) {
    viewer.setLight(clamp(state.light[0] + dy * 0.4, 0, DISK_MAX), state.light[1] - dx * 0.5);
    if (state.mode === "env") updateEnv();
  } else {
    viewer.setView(state.view[0] - dy * 0.3, state.view[1] - dx * 0.4);
  }
});

$("exposure").value = String(Math.log2(state.exposure));
$("exposure").addEventListener("input", () => {
  state.exposure = Math.pow(2, Number($("exposure").value));
  $("exposure-value").textContent = state.exposure.toFixed(2);
  draw();
});
$("alpha").addEventListener("input", () => {
  state.alphaDeg = Number($("alpha").value);
  $("alpha-value").textContent = `${state.alphaDeg}°`;
  draw();
});
$("mesh").value = state.mesh;
$("mesh").addEventListener("change", () => viewer.setMesh($("mesh").value).catch((e) => showError(e.message)));
$("mode").value = state.mode;
$("mode").addEventListener("change", () => viewer.setMode($("mode").value));

async function main() {
  $("run").textContent = run;
  canvas.width = 2 * state.size;
  canvas.height = state.size;
  $("exposure-value").textContent = state.exposure.toFixed(2);
  if (!gl) throw new Error("this browser has no WebGL2");
  buildProgram();
  await loadMaterial();
  await loadMesh();
  renderFrame();
  const m = manifest;
  $("status").textContent = m.kind === "btf"
    ? `${m.width}×${m.height} texels, ${m.view_table.directions.length} view slots × ${m.light_table.directions.length} lights, ${m.components} components`
    : `${m.width}×${m.height} photometric-stereo maps`;
  viewer.ready = true;
}

main().catch((e) => showError(`cannot show run ${run}: ${e.message}`));
