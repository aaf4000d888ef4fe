// rigd BTF viewer: relights a processed run on a mesh with WebGL2.
// The image is computed exactly as `rigd process render` computes it on
// the CPU (crates/process/src/relight.rs documents each step); the browser test
// compares the two. Left half: the BTF; right half: a plain texture.
// With the run's MDF (Wang et al., §4) the left half can also show the
// mesostructure's silhouettes and shadows, by depth peeling, as
// crates/process/src/silhouette.rs specifies them.
//
// URL parameters (all optional): mesh=flat|cylinder|cloth|sphere, light=θ,φ,
// view=θ,φ, size=N (pixels per half), exposure=X, mode=point|env,
// components=C (fewer PCA components for a GPU with less room),
// density=D (material tiles per world unit), silhouettes=mdf|none,
// shadows=mdf|none. window.rigdViewer exposes the state for tests and scripts.

const $ = (id) => document.getElementById(id);
const run = decodeURIComponent(location.pathname.split("/").filter(Boolean).pop() || "");
const params = new URLSearchParams(location.search);

// Constants shared with crates/process/src/relight.rs.
const CAMERA_DISTANCE = 4.5, FOV_DEG = 40, NEAR = 0.1, FAR = 20;
const BACKGROUND = 0.12, SHADOW_SOFTNESS = 0.05, DISPLAY_GAMMA = 2.2;
const MAX_ENTRIES = 64; // interpolation entries per table in the shader
// Constants shared with crates/process/src/silhouette.rs.
const MAX_PEEL_LAYERS = 4, SHADOW_MAP_SIZE = 512;
// A peel layer's texel where the pass drew nothing: its depth (w) lies
// beyond the far plane, so the next pass peels everything there.
const NO_FRAGMENT = [0, 0, 0, 2];
// The shadow map's values without a hit (silhouette.rs: +∞).
const NO_SHADOW = 1e30;
// How far (window depth) a fragment of the shading pass may be from the
// hit the peel passes found: both come from the same vertex shader, so a
// few ulps; 1e-6 is about 2e-4 world units at the mesh.
const HIT_EPSILON = 1e-6;
// Texture units: the material's 0–3 (uTex, uWeights, uTables, uEnv), the
// MDF's, the peel targets' while they are read, and one to create
// render targets on without disturbing the others.
const UNIT = { mdf: 4, mdfTables: 5, shadowMap: 6, hit: 7, prev: 8, layers: 9, scratch: 15 };
// Vertex attributes, at the same location in every program so that one
// vertex array serves them all.
const ATTRIBUTES = ["aPos", "aNormal", "aTangent", "aTex", "aParam"];

function parsePair(s, fallback) {
  if (!s) return fallback;
  const p = s.split(",").map(Number);
  return p.length === 2 && p.every(Number.isFinite) ? p : fallback;
}
// Tiles per world unit, as the mesh route takes them (0 < D ≤ 64).
function validDensity(x) {
  const d = Number(x);
  return Number.isFinite(d) && d > 0 && d <= 64 ? d : null;
}

const state = {
  mesh: params.get("mesh") || "flat",
  mode: params.get("mode") || "point",
  light: parsePair(params.get("light"), [30, 45]),
  view: parsePair(params.get("view"), [35, 270]),
  exposure: Number(params.get("exposure") || 1),
  alphaDeg: 0,
  size: Math.max(64, Math.min(1024, Number(params.get("size") || 512))),
  density: validDensity(params.get("density") || 1) || 1,
  // "mdf" only once the MDF is loaded and the GPU can peel (setMdfMode).
  silhouettes: "none",
  shadows: "none",
};

const viewer = {
  ready: false, error: null, frames: 0, kind: null,
  mdf: false,        // the run's MDF is loaded
  peelPasses: 0,     // peel passes the last frame drew (camera and light)
  state,
  setLight(theta, phi) { state.light = [theta, wrap(phi)]; draw(); },
  setView(theta, phi) { state.view = [clamp(theta, 0, 89), wrap(phi)]; draw(); },
  async setMesh(name) { state.mesh = name; $("mesh").value = name; await loadMesh(); draw(); },
  async setMode(mode) { state.mode = mode; $("mode").value = mode; if (mode === "env") updateEnv(); draw(); },
  setSilhouettes(mode) { return setMdfMode("silhouettes", mode); },
  setShadows(mode) { return setMdfMode("shadows", mode); },
  async setDensity(x) {
    const d = validDensity(x);
    if (d === null) throw new Error(`density ${x}: expected more than 0 and at most 64 tiles per unit`);
    state.density = d;
    await loadMesh();
    draw();
  },
  pixels: readLeftHalf,
  benchmark,
};
window.rigdViewer = viewer;

function clamp(x, lo, hi) { return Math.min(hi, Math.max(lo, x)); }
function wrap(phi) { return ((phi % 360) + 360) % 360; }
function showError(msg) {
  viewer.error = msg;
  showNotice(msg);
  $("status").textContent = "error";
}
// A message that does not stop the viewer (e.g. an MDF mode it cannot offer).
function showNotice(msg) {
  const m = $("message");
  m.textContent = msg;
  m.hidden = false;
}
const rad = (d) => (d * Math.PI) / 180;
function unitOf([theta, phi]) {
  const t = rad(theta), p = rad(phi);
  return [Math.sin(t) * Math.cos(p), Math.sin(t) * Math.sin(p), Math.cos(t)];
}
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
function unitVec(a, fallback) {
  const n = Math.hypot(...a);
  return n > 0 ? a.map((c) => c / n) : fallback;
}

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

// The shadow map's orthographic light frame (silhouette.rs, "Shadows"):
// w = L, right = unit(a × w), up = w × right, half-width R = 1.05 · max |p|;
// clip = (p·right, p·up, −p·L) / R, so window x, y are the texel grid (j
// counting up) and the depth grows with t = −p·L.
function lightFrame(L) {
  const a = Math.abs(L[2]) < 0.9 ? [0, 0, 1] : [1, 0, 0];
  const right = unitVec(cross(a, L), [1, 0, 0]);
  const up = cross(L, right);
  const R = meshGl.radius > 0 ? 1.05 * meshGl.radius : 1;
  const m = new Float32Array(16);
  for (let c = 0; c < 3; c++) {
    m[c * 4] = right[c] / R;
    m[c * 4 + 1] = up[c] / R;
    m[c * 4 + 2] = -L[c] / R;
  }
  m[15] = 1;
  return { vp: m, eye: [0, 0, 0], light: L, fromLight: true, right, up, R };
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
// (φ, direction index). Entries go to e{L,V}_i / e{L,V}_w. The MDF's view
// table (T = M) lives in its own texture, uMdfTables.
const INTERP = (T, row, tables = "uTables") => `
int e${T}_n; int e${T}_i[${MAX_ENTRIES}]; float e${T}_w[${MAX_ENTRIES}];
void push${T}(int index, float w) {
  if (e${T}_n < ${MAX_ENTRIES}) { e${T}_i[e${T}_n] = index; e${T}_w[e${T}_n] = w; e${T}_n++; }
}
vec2 member${T}(int k) { return texelFetch(${tables}, ivec2(k, ${row + 1}), 0).xy; }
void uniform${T}(vec4 ring, float scale) {
  int start = int(ring.y), n = int(ring.z);
  for (int k = 0; k < n; k++) push${T}(int(member${T}(start + k).y), scale / float(n));
}
void ring${T}(int r, float phi, float scale) {
  vec4 ring = texelFetch(${tables}, ivec2(r, ${row}), 0);
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
  vec4 first = texelFetch(${tables}, ivec2(0, ${row}), 0);
  vec4 last = texelFetch(${tables}, ivec2(rings - 1, ${row}), 0);
  if (theta <= first.x) {
    if (first.w > 0.5 || first.x <= 0.0) { ring${T}(0, phi, 1.0); }
    else { float t = theta / first.x; ring${T}(0, phi, t); uniform${T}(first, 1.0 - t); }
  } else if (theta >= last.x) {
    ring${T}(rings - 1, phi, 1.0);
  } else {
    int upper = 1;
    for (int r = 1; r < rings; r++) { upper = r; if (texelFetch(${tables}, ivec2(r, ${row}), 0).x > theta) break; }
    float below = texelFetch(${tables}, ivec2(upper - 1, ${row}), 0).x;
    float above = texelFetch(${tables}, ivec2(upper, ${row}), 0).x;
    float t = (theta - below) / (above - below);
    ring${T}(upper - 1, phi, 1.0 - t);
    ring${T}(upper, phi, t);
  }
}`;

// silhouette.rs, "The MDF offset at a surface point": uMdf holds layer v
// (the MDF for view direction v, mm along the ray below the top plane, −1
// without a measurement), read at the nearest texel only so that a −1 is
// never blended with a depth. Needs the varyings vN, vT.
const MDF_OFFSET = `
uniform highp sampler2DArray uMdf;
uniform highp sampler2D uMdfTables;  // the MDF's view table, rows 0–1 laid out as uTables'
uniform int uMdfRings; uniform int uMdfSize;
uniform float uMdfScale;             // mm to world units: 1 / (tile_mm · density)
${INTERP("M", 0, "uMdfTables")}
vec3 unitOr(vec3 v, vec3 fallback) {
  float len = length(v);
  return len > 0.0 ? v / len : fallback;
}
// A world direction in the local frame (t, b, n) of relight.rs, step 3.
vec3 toLocal(vec3 w) {
  vec3 n = unitOr(vN, vec3(0.0, 0.0, 1.0));
  vec3 t = unitOr(vT - n * dot(n, vT), vec3(1.0, 0.0, 0.0));
  vec3 b = cross(n, t);
  return vec3(dot(w, t), dot(w, b), dot(w, n));
}
// The offset (world units) at texture coordinate st for the local direction
// v (pointing away from the surface): the weighted mean over the view
// entries whose texel holds a measurement; 0, the surface at the mesh, when
// none does, so gaps in the laser data never punch holes.
float mdfOffset(vec2 st, vec3 v) {
  interpolateM(v, uMdfRings);
  ivec2 at = clamp(ivec2(floor(fract(vec2(st.x, -st.y)) * float(uMdfSize))), ivec2(0), ivec2(uMdfSize - 1));
  float sum = 0.0, weight = 0.0;
  for (int e = 0; e < eM_n; e++) {
    float mm = texelFetch(uMdf, ivec3(at, eM_i[e]), 0).r;
    if (mm >= 0.0) { sum += eM_w[e] * mm; weight += eM_w[e]; }
  }
  return weight > 0.0 ? sum / weight * uMdfScale : 0.0;
}`;

// What shadingSource(true) adds to the shading pass.
const MDF_SHADING = `
uniform int uSilhouettes;            // 1: draw only the layer walk's hit
uniform int uShadows;                // 1: the MDF shadow map darkens
uniform highp sampler2D uHit;        // per pixel of this half, x: window depth of the hit (> 1: none)
uniform highp sampler2D uShadowMap;  // per texel, from the light: y the hit's t + d (meso), z its t (mesh)
uniform vec3 uShadowRight; uniform vec3 uShadowUp; uniform float uShadowR;
${MDF_OFFSET}
// The fragment the walk hit (the depth test then keeps the nearest of the
// fragments this close to it; the background stays where nothing was hit).
bool isHit() {
  float hit = texelFetch(uHit, ivec2(gl_FragCoord.xy), 0).x;
  return hit <= 1.0 && abs(gl_FragCoord.z - hit) <= ${HIT_EPSILON.toExponential()};
}
// silhouette.rs's shadow lookup: 0 where the map's hit lies nearer the
// light than this fragment both as mesh (t; so a surface does not shadow
// itself where the MDF jumps between texels) and as mesostructure (z; so
// light passes where the occluder's mesostructure lies deeper), each by
// more than the bias; else 1, and 1 outside the map.
float mdfLit(vec3 n, vec3 l) {
  float size = ${SHADOW_MAP_SIZE.toFixed(1)};
  vec2 q = (vec2(dot(vP, uShadowRight), dot(vP, uShadowUp)) / uShadowR + 1.0) * 0.5 * size;
  if (any(lessThan(q, vec2(0.0))) || any(greaterThanEqual(q, vec2(size)))) return 1.0;
  vec4 map = texelFetch(uShadowMap, ivec2(q), 0);
  float t = -dot(vP, uLight);
  float z = t + (l.z > 0.0 ? mdfOffset(vTex, l) : 0.0);   // d_L: 0 with L below the local horizon
  float c = max(dot(n, uLight), 0.05);
  float bias = 2.0 * uShadowR / size * (2.0 + min(sqrt(max(1.0 - c * c, 0.0)) / c, 20.0));
  return t > map.z + bias && z > map.y + bias ? 0.0 : 1.0;
}`;

// One depth-peel pass (Everitt's depth peeling): the mesh drawn with the
// depth test, fragments at or in front of the previous layer discarded,
// so each pixel keeps the nearest fragment behind that layer. It stores
// what the layer walk needs: the distance t along the ray (from the eye;
// for the light t = −p·L), the MDF offset d for the direction the ray
// arrives from, whether the fragment faces the ray, and its depth.
const PEEL_FRAGMENT = `#version 300 es
precision highp float; precision highp int; precision highp sampler2DArray;
in vec3 vP; in vec3 vN; in vec3 vT; in vec2 vTex;
uniform highp sampler2D uPrev;  // layer k − 1
uniform int uLayer;             // k, 0 the nearest
uniform int uFromLight;         // 1: the light's parallel rays along −L; 0: the camera's
uniform vec3 uEye; uniform vec3 uLight;
out vec4 outLayer;              // t, d, front (1 or 0), window depth
${MDF_OFFSET}
void main() {
  if (uLayer > 0 && gl_FragCoord.z <= texelFetch(uPrev, ivec2(gl_FragCoord.xy), 0).w) discard;
  vec3 ray = uFromLight == 1 ? -uLight : unitOr(vP - uEye, -uLight);
  float t = uFromLight == 1 ? -dot(vP, uLight) : distance(uEye, vP);
  // Back along the ray at a front fragment, onwards at a back one: both
  // point away from the surface (gl_FrontFacing: the side the normals
  // point to faces the ray's origin).
  vec3 away = gl_FrontFacing ? -ray : ray;
  outLayer = vec4(t, mdfOffset(vTex, toLocal(away)), gl_FrontFacing ? 1.0 : 0.0, gl_FragCoord.z);
}`;

// A triangle covering the whole target, for the per-pixel passes.
const FULLSCREEN_VERTEX = `#version 300 es
void main() {
  gl_Position = vec4(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0, 0.0, 1.0);
}`;

// silhouette.rs's layer walk over the peeled layers, near to far, with a
// pending front fragment f. Writes the hit's window depth (x; 2 without a
// hit), and the shadow map's values t + d (y) and t (z), +∞ without a hit.
const layerIds = [...Array(MAX_PEEL_LAYERS).keys()];
const RESOLVE_FRAGMENT = `#version 300 es
precision highp float; precision highp int;
${layerIds.map((k) => `uniform highp sampler2D uLayer${k};`).join("\n")}
out vec4 outHit;
void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 layer[${MAX_PEEL_LAYERS}] = vec4[${MAX_PEEL_LAYERS}](${layerIds.map((k) => `texelFetch(uLayer${k}, px, 0)`).join(", ")});
  int hit = -1, pending = -1;
  for (int k = 0; k < ${MAX_PEEL_LAYERS} && hit < 0; k++) {
    vec4 f = layer[k];
    if (f.w > 1.0) break;                     // no fragment here, so none farther
    if (f.z > 0.5) {                          // front: a second one hits the pending one (an open mesh)
      if (pending >= 0) hit = pending; else pending = k;
    } else if (pending < 0) {
      hit = k;                                // back, nothing pending: the inside of an open mesh
    } else if (layer[pending].y + f.y <= f.x - layer[pending].x) {
      hit = pending;                          // d_f + d_b ≤ t_b − t_f: mesostructure in [f, b]
    } else {
      pending = -1;                           // the ray passes between the surfaces
    }
  }
  if (hit < 0) hit = pending;                 // an open sheet's interval runs to infinity
  if (hit < 0) { outHit = vec4(2.0, ${NO_SHADOW.toExponential()}, ${NO_SHADOW.toExponential()}, 0.0); return; }
  vec4 h = layer[hit];
  outHit = vec4(h.w, h.x + (h.z > 0.5 ? h.y : 0.0), h.x, 0.0);   // an unpaired back fragment: d = 0
}`;

// The shading pass. shadingSource(false) is the viewer without the MDF
// (what relight.rs renders); shadingSource(true) adds the silhouette and
// shadow tests of silhouette.rs around the same shading.
const shadingSource = (mdf) => `#version 300 es
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
${INTERP("V", 2)}${mdf ? MDF_SHADING : ""}
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
void main() {${mdf ? `
  if (uSilhouettes == 1 && !isHit()) discard;` : ""}
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
  }${mdf ? `
  if (uShadows == 1 && uEnvMode == 0) shadow *= mdfLit(n, l);` : ""}
  vec3 linear = clamp(uExposure * shadow * value, 0.0, 1.0);
  outColor = vec4(pow(linear, vec3(1.0 / ${DISPLAY_GAMMA.toFixed(1)})), 1.0);
}`;

const canvas = $("canvas");
const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
// Float render targets (the peel layers) need this extension.
const floatTargets = gl ? gl.getExtension("EXT_color_buffer_float") : null;
let manifest = null, mesh = null, meshGl = null;
let textures = {};
// plain: the viewer without the MDF; mdf, peel, resolve: built on the first
// use of an MDF mode (ensureMdf).
const programs = { plain: null, mdf: null, peel: null, resolve: null };
// The peel targets of the camera (view) and of the light.
const targets = { view: null, light: null };
// The loaded MDF (loadMdf), or null with mdfMissing saying why.
let mdf = null, mdfMissing = "loading";

function compile(type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s) || "shader");
  return s;
}

// A linked program and its uniforms' locations by name.
function buildProgram(vertex, fragment) {
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl.VERTEX_SHADER, vertex));
  gl.attachShader(program, compile(gl.FRAGMENT_SHADER, fragment));
  ATTRIBUTES.forEach((name, loc) => gl.bindAttribLocation(program, loc, name));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program) || "link");
  const uniforms = {};
  const n = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const info = gl.getActiveUniform(program, i);
    uniforms[info.name.replace(/\[0\]$/, "")] = gl.getUniformLocation(program, info.name);
  }
  return { program, uniforms };
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

function textureArray(unit, internal, format, w, h, layers, data, wrapMode, type = gl.HALF_FLOAT, filter = gl.LINEAR) {
  const t = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
  gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, w, h, layers, 0, format, type, data);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, filter);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, wrapMode);
  gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, wrapMode);
  return t;
}

// Row 2T: rings (θ, first member, count, pole); row 2T+1: members (φ, index).
function tablesTexture(tables, unit = 2) {
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
  return texture2d(unit, gl.RGBA32F, gl.RGBA, gl.FLOAT, width, rows.length, data, gl.NEAREST);
}

async function fetchJson(url) {
  const r = await fetch(url);
  const body = await r.json().catch(() => null);
  if (!r.ok) throw new Error((body && body.detail) || `${url}: HTTP ${r.status}`);
  return body;
}

function checkRings(table) {
  for (const ring of table.rings)
    if (ring.members.length + 2 > MAX_ENTRIES) throw new Error(`a ring of ${ring.members.length} directions: the viewer takes at most ${MAX_ENTRIES - 2}`);
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
    for (const t of [manifest.light_table, manifest.view_table]) checkRings(t);
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

// The run's MDF (Wang et al., §3), if it has one: the depth layers as an
// R32F array texture and the view table. Never fatal: without it the MDF
// toggles stay disabled, their title saying why.
async function loadMdf() {
  try {
    const m = await fetchJson(`/api/v1/runs/${encodeURIComponent(run)}/mdf`);
    if (m.version !== 1) throw new Error(`unknown MDF version ${m.version}`);
    const n = m.size, views = m.views;
    if (!(Number.isInteger(n) && n > 0 && Number.isInteger(views) && views > 0)) throw new Error(`MDF of ${n}² texels × ${views} views`);
    if (m.view_table.directions.length !== views) throw new Error(`MDF view table of ${m.view_table.directions.length} directions for ${views} layers`);
    checkRings(m.view_table);
    if (!(m.tile_mm > 0 && Number.isFinite(m.tile_mm))) throw new Error(`MDF tile of ${m.tile_mm} mm`);
    if (n > gl.getParameter(gl.MAX_TEXTURE_SIZE) || views > gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS))
      throw new Error(`an MDF of ${n}² texels × ${views} views is more than this GPU holds`);
    if (m.depth.encoding !== "f32le" || m.depth.bytes !== 4 * views * n * n) throw new Error(`MDF depth section of ${m.depth.bytes} bytes (${m.depth.encoding})`);
    const r = await fetch(m.data_url);
    if (!r.ok) throw new Error(`MDF data: HTTP ${r.status}`);
    const blob = await r.arrayBuffer();
    if (blob.byteLength < m.depth.offset + m.depth.bytes) throw new Error(`MDF data of ${blob.byteLength} bytes, short of the manifest's`);
    const depth = new Float32Array(blob, m.depth.offset, m.depth.bytes / 4);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    const texture = textureArray(UNIT.mdf, gl.R32F, gl.RED, n, n, views, depth, gl.REPEAT, gl.FLOAT, gl.NEAREST);
    const tables = tablesTexture([m.view_table], UNIT.mdfTables);
    mdf = { size: n, rings: m.view_table.rings.length, tileMm: m.tile_mm, texture, tables };
    mdfMissing = null;
  } catch (e) {
    mdf = null;
    mdfMissing = `no MDF: ${e.message}`;
  }
  viewer.mdf = mdf !== null;
  for (const id of ["silhouettes", "shadows"]) {
    $(id).disabled = !mdf;
    $(id).closest("label").title = mdf ? "" : mdfMissing;
  }
}

async function loadMesh() {
  mesh = await fetchJson(`/api/v1/runs/${encodeURIComponent(run)}/btf/mesh/${state.mesh}?density=${state.density}`);
  if (meshGl) {
    gl.deleteVertexArray(meshGl.vao);
    meshGl.buffers.forEach((b) => gl.deleteBuffer(b));
  }
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const buffers = [];
  const attr = (name, data, size) => {
    const loc = ATTRIBUTES.indexOf(name);
    const b = gl.createBuffer();
    buffers.push(b);
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
  buffers.push(ib);
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
  gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, new Uint32Array(mesh.indices), gl.STATIC_DRAW);
  gl.bindVertexArray(null);
  // The shadow map's half-width comes from the farthest vertex.
  let radius = 0;
  for (let v = 0; v < mesh.positions.length; v += 3)
    radius = Math.max(radius, Math.hypot(mesh.positions[v], mesh.positions[v + 1], mesh.positions[v + 2]));
  meshGl = { vao, buffers, count: mesh.indices.length, radius };
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

function setUniforms(p, shading) {
  const uniforms = p.uniforms;
  const cam = camera(state.view);
  const L = unitOf(state.light);
  gl.uniformMatrix4fv(uniforms.uVP, false, cam.vp);
  gl.uniform3fv(uniforms.uLight, L);
  gl.uniform3fv(uniforms.uEye, cam.eye);
  gl.uniform1f(uniforms.uExposure, state.exposure);
  gl.uniform1f(uniforms.uAlpha, rad(state.alphaDeg));
  gl.uniform1i(uniforms.uShading, shading);
  gl.uniform1i(uniforms.uKind, manifest.kind === "btf" ? 0 : 1);
  gl.uniform1i(uniforms.uEnvMode, envMode() ? 1 : 0);
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
const envMode = () => state.mode === "env" && manifest.kind === "btf";

// The MDF's textures and its scale to world units: a tile spans
// 1 / density world units.
function setMdfUniforms(p) {
  const u = p.uniforms;
  gl.uniform1i(u.uMdf, UNIT.mdf);
  gl.uniform1i(u.uMdfTables, UNIT.mdfTables);
  gl.uniform1i(u.uMdfRings, mdf.rings);
  gl.uniform1i(u.uMdfSize, mdf.size);
  gl.uniform1f(u.uMdfScale, 1 / (mdf.tileMm * state.density));
}

function bindTexture(unit, texture) {
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_2D, texture);
}

// Turns an MDF mode ("silhouettes" or "shadows") to "mdf" or "none" and
// returns the mode in force: "mdf" is refused, with a message, when the run
// has no MDF (a notice) or the GPU cannot peel (an error).
function setMdfMode(key, mode) {
  if (mode !== "mdf" && mode !== "none") throw new Error(`${key}: expected "mdf" or "none", not ${mode}`);
  if (mode === "mdf") {
    if (!mdf) {
      showNotice(`MDF ${key} are not available: ${mdfMissing}`);
      mode = "none";
    } else {
      try { ensureMdf(); } catch (e) { showError(`MDF ${key}: ${e.message}`); mode = "none"; }
    }
  }
  state[key] = mode;
  $(key).checked = mode === "mdf";
  draw();
  return mode;
}

// Compiles the MDF programs and allocates the peel targets, once.
function ensureMdf() {
  if (programs.peel) return;
  if (!floatTargets) throw new Error("this browser's WebGL2 cannot render to float textures (EXT_color_buffer_float), which depth peeling needs");
  const built = {
    mdf: buildProgram(VERTEX, shadingSource(true)),
    peel: buildProgram(VERTEX, PEEL_FRAGMENT),
    resolve: buildProgram(FULLSCREEN_VERTEX, RESOLVE_FRAGMENT),
  };
  targets.view = peelTargets(state.size);
  targets.light = peelTargets(SHADOW_MAP_SIZE);
  Object.assign(programs, built);
}

// The render targets of one peel (the camera's or the light's), size²
// texels: per pass an RGBA32F layer (t, d, front, depth) with the depth
// buffer they share, and the walk's result (RGBA32F: the hit's depth,
// t + d, t).
function peelTargets(size) {
  const depth = gl.createRenderbuffer();
  gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
  gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT32F, size, size);
  const framebuffer = (texture, withDepth) => {
    const fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    if (withDepth) gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`this GPU cannot render to a ${size}² float target (status 0x${status.toString(16)})`);
    return fb;
  };
  const layers = layerIds.map(() => texture2d(UNIT.scratch, gl.RGBA32F, gl.RGBA, gl.FLOAT, size, size, null, gl.NEAREST));
  const hit = texture2d(UNIT.scratch, gl.RGBA32F, gl.RGBA, gl.FLOAT, size, size, null, gl.NEAREST);
  return { size, layers, framebuffers: layers.map((t) => framebuffer(t, true)), hit, hitFramebuffer: framebuffer(hit, false) };
}

// The camera's rays, for peelAndWalk.
function cameraRays() {
  const cam = camera(state.view);
  return { vp: cam.vp, eye: cam.eye, light: unitOf(state.light), fromLight: false };
}

// MAX_PEEL_LAYERS peel passes of the mesh along `rays` into t's layers,
// then the layer walk per pixel into t.hit. Returns the peel passes drawn.
function peelAndWalk(t, rays) {
  const peel = programs.peel, u = peel.uniforms;
  gl.useProgram(peel.program);
  gl.bindVertexArray(meshGl.vao);
  gl.viewport(0, 0, t.size, t.size);
  gl.enable(gl.DEPTH_TEST);
  gl.depthFunc(gl.LESS);
  gl.uniformMatrix4fv(u.uVP, false, rays.vp);
  gl.uniform3fv(u.uEye, rays.eye);
  gl.uniform3fv(u.uLight, rays.light);
  gl.uniform1i(u.uFromLight, rays.fromLight ? 1 : 0);
  gl.uniform1i(u.uPrev, UNIT.prev);
  setMdfUniforms(peel);
  for (let k = 0; k < MAX_PEEL_LAYERS; k++) {
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.framebuffers[k]);
    gl.clearBufferfv(gl.COLOR, 0, NO_FRAGMENT);
    gl.clearBufferfv(gl.DEPTH, 0, [1]);
    // Pass 0 reads no previous layer; never bind the layer being drawn.
    bindTexture(UNIT.prev, k > 0 ? t.layers[k - 1] : null);
    gl.uniform1i(u.uLayer, k);
    gl.drawElements(gl.TRIANGLES, meshGl.count, gl.UNSIGNED_INT, 0);
  }
  const walk = programs.resolve;
  gl.useProgram(walk.program);
  gl.bindFramebuffer(gl.FRAMEBUFFER, t.hitFramebuffer);
  gl.disable(gl.DEPTH_TEST);
  gl.bindVertexArray(null);
  t.layers.forEach((layer, k) => {
    bindTexture(UNIT.layers + k, layer);
    gl.uniform1i(walk.uniforms[`uLayer${k}`], UNIT.layers + k);
  });
  gl.drawArrays(gl.TRIANGLES, 0, 3);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  return MAX_PEEL_LAYERS;
}

// The MDF shading pass's own uniforms: which tests run, the camera's walk
// result and the shadow map with its light frame.
function setMdfShadingUniforms(p, silhouettes, light) {
  const u = p.uniforms;
  setMdfUniforms(p);
  gl.uniform1i(u.uSilhouettes, silhouettes ? 1 : 0);
  gl.uniform1i(u.uShadows, light ? 1 : 0);
  gl.uniform1i(u.uHit, UNIT.hit);
  gl.uniform1i(u.uShadowMap, UNIT.shadowMap);
  bindTexture(UNIT.hit, silhouettes ? targets.view.hit : null);
  bindTexture(UNIT.shadowMap, light ? targets.light.hit : null);
  if (light) {
    gl.uniform3fv(u.uShadowRight, light.right);
    gl.uniform3fv(u.uShadowUp, light.up);
    gl.uniform1f(u.uShadowR, light.R);
  }
}

function renderFrame() {
  if (!programs.plain || !manifest || !meshGl) return;
  const s = state.size;
  // The MDF passes first, into their own targets; shadows need the point light.
  const silhouettes = state.silhouettes === "mdf";
  const light = state.shadows === "mdf" && !envMode() ? lightFrame(unitOf(state.light)) : null;
  let passes = 0;
  if (light) passes += peelAndWalk(targets.light, light);
  if (silhouettes) passes += peelAndWalk(targets.view, cameraRays());
  gl.enable(gl.DEPTH_TEST);
  gl.depthFunc(gl.LESS);
  gl.disable(gl.CULL_FACE);
  gl.clearColor(BACKGROUND, BACKGROUND, BACKGROUND, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.bindVertexArray(meshGl.vao);
  for (const [x, shading] of [[0, 0], [s, 1]]) {
    // The BTF half with an MDF mode on takes the MDF shading pass.
    const p = shading === 0 && (silhouettes || light) ? programs.mdf : programs.plain;
    gl.useProgram(p.program);
    gl.viewport(x, 0, s, s);
    setUniforms(p, shading);
    if (p === programs.mdf) setMdfShadingUniforms(p, silhouettes, light);
    gl.drawElements(gl.TRIANGLES, meshGl.count, gl.UNSIGNED_INT, 0);
  }
  viewer.peelPasses = passes;
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
for (const key of ["silhouettes", "shadows"])
  $(key).addEventListener("change", () => setMdfMode(key, $(key).checked ? "mdf" : "none"));

async function main() {
  $("run").textContent = run;
  canvas.width = 2 * state.size;
  canvas.height = state.size;
  $("exposure-value").textContent = state.exposure.toFixed(2);
  if (!gl) throw new Error("this browser has no WebGL2");
  programs.plain = buildProgram(VERTEX, shadingSource(false));
  await loadMaterial();
  await loadMdf();
  await loadMesh();
  for (const key of ["silhouettes", "shadows"])
    if (params.get(key) === "mdf") setMdfMode(key, "mdf");
  renderFrame();
  const m = manifest;
  $("status").textContent = m.kind === "btf"
    ? `${m.width}×${m.height} texels, ${m.view_table.directions.length} view slots × ${m.light_table.directions.length} lights, ${m.components} components`
    : `${m.width}×${m.height} photometric-stereo maps`;
  viewer.ready = true;
}

main().catch((e) => showError(`cannot show run ${run}: ${e.message}`));
