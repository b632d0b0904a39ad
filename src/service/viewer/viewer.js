// The service's page: the timelines (home) or one timeline in 3D (viewer), from this service
// alone. The viewer draws each frame's baked glTF (`baked.glb`) with WebGL2: the HDR radiance
// per vertex (`_RADIANCE`) through the same tone curve as the files' vertex colours, or a false
// colour per patch (the primitive's `extras.patches` names each triangle's patch). The unlit
// side of a triangle lit on its other side is cut away, as in the previews (`cutaway`).
'use strict';

const $ = (id) => document.getElementById(id);

/** A request to this service; a problem (RFC 9457) becomes an Error with its detail. */
async function request(path, options = {}) {
  const response = await fetch(path, options);
  if (!response.ok) {
    let detail = `${response.status} ${response.statusText}`;
    try {
      const problem = await response.json();
      detail = problem.detail || problem.title || detail;
    } catch (_) { /* not JSON */ }
    const error = new Error(detail);
    error.status = response.status;
    throw error;
  }
  return response;
}
const getJson = async (path) => (await request(path)).json();

const fmt = (x, digits = 3) => (Number.isFinite(x) ? Number(x.toPrecision(digits)).toString() : '–');
const rgb = (c) => `${fmt(c[0])}, ${fmt(c[1])}, ${fmt(c[2])}`;
const luminance = (c) => 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
function element(tag, props = {}, children = []) {
  const e = Object.assign(document.createElement(tag), props);
  e.append(...children);
  return e;
}

// ---------------------------------------------------------------------------------------------
// Home: the timelines, and a scene to bake.

async function home() {
  $('home').hidden = false;
  document.title = 'radiosity';
  const drop = $('drop');
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => {
    e.preventDefault();
    drop.classList.remove('over');
    if (e.dataTransfer.files.length) bake(e.dataTransfer.files[0], e.dataTransfer.files[0].name);
  });
  $('file').addEventListener('change', (e) => {
    if (e.target.files.length) bake(e.target.files[0], e.target.files[0].name);
  });
  getJson('/v1/samples').then(({ samples }) => {
    for (const s of samples) {
      const button = element('button', { type: 'button', title: s.description, textContent: s.name });
      button.addEventListener('click', async () => {
        try {
          bake(await (await request(`/v1/samples/${s.name}`)).blob(), s.name);
        } catch (e) { $('post-error').textContent = e.message; }
      });
      $('samples').append(button);
    }
  });
  await listTimelines();
}

/** POSTs `body` (a glTF file) with the chosen preset and fps, then opens its viewer. */
async function bake(body, name) {
  $('post-error').textContent = '';
  const binary = name.toLowerCase().endsWith('.glb');
  const query = new URLSearchParams({ preset: $('preset').value, fps: $('fps').value });
  try {
    const response = await request(`/v1/timelines?${query}`, {
      method: 'POST',
      headers: { 'content-type': binary ? 'model/gltf-binary' : 'model/gltf+json' },
      body,
    });
    const created = await response.json();
    location.href = `/v1/timelines/${created.id}/viewer`;
  } catch (e) {
    $('post-error').textContent = `${name}: ${e.message}`;
  }
}

async function listTimelines() {
  const { timelines } = await getJson('/v1/timelines');
  const body = $('timelines').tBodies[0];
  body.replaceChildren();
  $('no-timelines').hidden = timelines.length > 0;
  for (const t of timelines) {
    const row = element('tr', {}, [
      element('td', {}, [element('a', { href: `/v1/timelines/${t.id}/viewer`, textContent: t.id })]),
      element('td', { textContent: t.status }),
      element('td'), element('td'), element('td'),
    ]);
    const remove = element('button', { type: 'button', textContent: 'delete' });
    remove.addEventListener('click', async () => {
      await request(`/v1/timelines/${t.id}`, { method: 'DELETE' }).catch(() => {});
      listTimelines();
    });
    row.cells[4].append(remove);
    body.append(row);
    getJson(`/v1/timelines/${t.id}`).then((s) => {
      row.cells[1].textContent = s.status;
      row.cells[2].textContent = s.frames;
      row.cells[3].textContent = s.patches;
    }).catch(() => {});
  }
}

// ---------------------------------------------------------------------------------------------
// Binary glTF: the JSON chunk and typed views of the accessors the viewer reads.

function parseGlb(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength < 12 || view.getUint32(0, true) !== 0x46546c67) throw new Error('not a binary glTF');
  let json = null;
  let bin = null;
  for (let at = 12; at + 8 <= buffer.byteLength;) {
    const length = view.getUint32(at, true);
    const type = view.getUint32(at + 4, true);
    if (type === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, at + 8, length)));
    if (type === 0x004e4942) bin = { buffer, offset: at + 8 };
    at += 8 + length;
  }
  const accessor = (index) => {
    const a = json.accessors[index];
    const v = json.bufferViews[a.bufferView];
    const n = a.count * { SCALAR: 1, VEC3: 3 }[a.type];
    const offset = bin.offset + (v.byteOffset || 0) + (a.byteOffset || 0);
    return a.componentType === 5126 ? new Float32Array(buffer, offset, n) : new Uint32Array(buffer, offset, n);
  };
  return { json, accessor };
}

/**
 * A frame's drawable arrays from its glb: one vertex per triangle corner (so each triangle can
 * carry its patch), positions relative to `origin` (the first node's translation, the scene's
 * centre, kept out of f32), HDR radiance, and the patch id.
 */
function frameFromGlb(buffer) {
  const { json, accessor } = parseGlb(buffer);
  const meshNodes = json.nodes.filter((n) => n.mesh !== undefined);
  const origin = (meshNodes[0] && meshNodes[0].translation) || [0, 0, 0];
  let corners = 0;
  for (const node of meshNodes) {
    for (const p of json.meshes[node.mesh].primitives) corners += json.accessors[p.indices].count;
  }
  const position = new Float32Array(corners * 3);
  const radiance = new Float32Array(corners * 3);
  const patch = new Uint32Array(corners);
  const nodeOfPatch = new Map();
  const min = [Infinity, Infinity, Infinity];
  const max = [-Infinity, -Infinity, -Infinity];
  let k = 0;
  for (const node of meshNodes) {
    const t = node.translation || [0, 0, 0];
    const shift = [t[0] - origin[0], t[1] - origin[1], t[2] - origin[2]];
    for (const p of json.meshes[node.mesh].primitives) {
      const P = accessor(p.attributes.POSITION);
      const R = accessor(p.attributes._RADIANCE);
      const I = accessor(p.indices);
      const T = accessor(p.extras.patches);
      for (let c = 0; c < I.length; c++, k++) {
        const v = I[c];
        for (let a = 0; a < 3; a++) {
          const x = P[3 * v + a] + shift[a];
          position[3 * k + a] = x;
          radiance[3 * k + a] = R[3 * v + a];
          if (x < min[a]) min[a] = x;
          if (x > max[a]) max[a] = x;
        }
        patch[k] = T[(c / 3) | 0];
        nodeOfPatch.set(patch[k], node.name);
      }
    }
  }
  const cameras = json.nodes.filter((n) => n.camera !== undefined).map((n) => ({
    name: n.name || 'camera',
    rotation: n.rotation || [0, 0, 0, 1],
    translation: (n.translation || [0, 0, 0]).map((x, a) => x - origin[a]),
    projection: json.cameras[n.camera],
  }));
  const extras = json.scenes[0].extras || {};
  return { origin, position, radiance, patch, corners, nodeOfPatch, min, max, cameras, time: extras.time };
}

/** A patch is unlit at or below this share of the frame's brightest luminance (`tonemap::UNLIT`). */
const UNLIT_SHARE = 1e-4;

/**
 * The previews' cutaway (`output::preview_image`): the unlit side of a triangle whose other
 * side is lit is not drawn. A closed room of double-sided walls (as Blender exports every
 * material) seen from outside then shows its lit inside through the walls' dark outer sides,
 * as a room of one-sided walls does with its back faces culled. Lit is the patch's radiance in
 * `solution` (the frame's, `parseSolution`) above `UNLIT_SHARE` of the brightest patch's.
 * The glb draws the two sides of a triangle as two triangles on the same corners, turning
 * opposite ways: those are paired here. Returns the frame's arrays without the cut triangles,
 * and how many were cut.
 */
function cutaway(frame, solution) {
  const L = solution.radiance;
  const y = (p) => 0.2126 * L[3 * p] + 0.7152 * L[3 * p + 1] + 0.0722 * L[3 * p + 2];
  let brightest = 0;
  for (let p = 0; p < solution.patches; p++) brightest = Math.max(brightest, y(p));
  const lit = (p) => p < solution.patches && y(p) > UNLIT_SHARE * brightest;
  const { position, patch } = frame;
  const triangles = frame.corners / 3;
  // Each triangle's corners from the least (as a string, exact for f32 positions): the two
  // sides of one triangle list the same three, the second and third swapped.
  const other = new Int32Array(triangles).fill(-1);
  const open = new Map();
  for (let t = 0; t < triangles; t++) {
    const c = [0, 1, 2].map((k) => `${position[9 * t + 3 * k]},${position[9 * t + 3 * k + 1]},${position[9 * t + 3 * k + 2]}`);
    if (new Set(c).size < 3) continue; // degenerate: no sides to tell apart
    const first = c.indexOf(c.reduce((a, b) => (b < a ? b : a)));
    const [b, d] = [c[(first + 1) % 3], c[(first + 2) % 3]];
    const key = b < d ? `${c[first]};${b};${d}` : `${c[first]};${d};${b}`;
    const turn = b < d;
    const seen = open.get(key);
    if (seen && seen.turn !== turn) {
      other[t] = seen.t;
      other[seen.t] = t;
      open.delete(key);
    } else if (!seen) open.set(key, { t, turn });
  }
  const keep = [];
  for (let t = 0; t < triangles; t++) {
    const p = patch[3 * t];
    if (!(other[t] >= 0 && !lit(p) && lit(patch[3 * other[t]]))) keep.push(t);
  }
  if (keep.length === triangles) return { arrays: frame, cut: 0 };
  const kept = { ...frame, position: new Float32Array(9 * keep.length), radiance: new Float32Array(9 * keep.length), patch: new Uint32Array(3 * keep.length), corners: 3 * keep.length };
  keep.forEach((t, k) => {
    kept.position.set(position.subarray(9 * t, 9 * t + 9), 9 * k);
    kept.radiance.set(frame.radiance.subarray(9 * t, 9 * t + 9), 9 * k);
    kept.patch.set(patch.subarray(3 * t, 3 * t + 3), 3 * k);
  });
  return { arrays: kept, cut: triangles - keep.length };
}

// ---------------------------------------------------------------------------------------------
// 4×4 matrices, column-major as WebGL takes them.

const mat4 = {
  multiply(a, b) {
    const o = new Float32Array(16);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      o[c * 4 + r] = s;
    }
    return o;
  },
  perspective(yfov, aspect, near, far) {
    const f = 1 / Math.tan(yfov / 2);
    const o = new Float32Array(16);
    o[0] = f / aspect; o[5] = f; o[11] = -1;
    if (far) { o[10] = (far + near) / (near - far); o[14] = (2 * far * near) / (near - far); } else { o[10] = -1; o[14] = -2 * near; }
    return o;
  },
  orthographic(xmag, ymag, near, far) {
    const o = new Float32Array(16);
    o[0] = 1 / xmag; o[5] = 1 / ymag; o[10] = 2 / (near - far); o[14] = (far + near) / (near - far); o[15] = 1;
    return o;
  },
  /** World to camera for a camera at `eye` with axes `x`, `y`, `z` (looking down −z). */
  view(eye, x, y, z) {
    const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
  },
};

/** The axes of a unit quaternion's rotation. */
function quaternionAxes([x, y, z, w]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)],
    [2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)],
    [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)],
  ];
}

// ---------------------------------------------------------------------------------------------
// WebGL2.

const VERTEX = `#version 300 es
in vec3 a_position;
in vec3 a_radiance;
in uint a_patch;
uniform mat4 u_matrix;
out vec3 v_radiance;
flat out uint v_patch;
void main() {
  v_radiance = a_radiance;
  v_patch = a_patch;
  gl_Position = u_matrix * vec4(a_position, 1.0);
}`;

// Mode 0: the tone curve of the baked files (x = exposure · radiance, x / (1 + Y(x)) clamped,
// Rec. 709 Y), then sRGB; mode 1: the overlay's colour of the patch; mode 2: the patch id + 1
// in RGBA8, for picking.
const FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
in vec3 v_radiance;
flat in uint v_patch;
uniform float u_exposure;
uniform int u_mode;
uniform highp sampler2D u_overlay;
out vec4 colour;
vec3 srgb(vec3 c) {
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() {
  if (u_mode == 2) {
    uint id = v_patch + 1u;
    colour = vec4(uvec4(id, id >> 8, id >> 16, id >> 24) & 255u) / 255.0;
    return;
  }
  if (u_mode == 1) {
    colour = texelFetch(u_overlay, ivec2(int(v_patch % 2048u), int(v_patch / 2048u)), 0);
    return;
  }
  vec3 x = max(v_radiance, 0.0) * u_exposure;
  float y = dot(x, vec3(0.2126, 0.7152, 0.0722));
  colour = vec4(srgb(clamp(x / (1.0 + y), 0.0, 1.0)), 1.0);
}`;

class Renderer {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext('webgl2', { antialias: true, preserveDrawingBuffer: true });
    if (!gl) throw new Error('this browser has no WebGL2');
    this.gl = gl;
    const shader = (type, source) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, source);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    };
    const program = gl.createProgram();
    gl.attachShader(program, shader(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, shader(gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    this.program = program;
    this.uniform = {};
    for (const u of ['u_matrix', 'u_exposure', 'u_mode', 'u_overlay']) this.uniform[u] = gl.getUniformLocation(program, u);
    this.overlay = gl.createTexture();
    this.pickTarget = null;
  }

  /** GPU buffers for a frame's arrays; `release` frees them. */
  upload(frame) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buffers = [];
    const attribute = (name, data, size, integer) => {
      const location = gl.getAttribLocation(this.program, name);
      const buffer = gl.createBuffer();
      buffers.push(buffer);
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(location);
      if (integer) gl.vertexAttribIPointer(location, size, gl.UNSIGNED_INT, 0, 0);
      else gl.vertexAttribPointer(location, size, gl.FLOAT, false, 0, 0);
    };
    attribute('a_position', frame.position, 3, false);
    attribute('a_radiance', frame.radiance, 3, false);
    attribute('a_patch', frame.patch, 1, true);
    gl.bindVertexArray(null);
    return { vao, count: frame.corners, release: () => { gl.deleteVertexArray(vao); buffers.forEach((b) => gl.deleteBuffer(b)); } };
  }

  /** Per-patch RGBA8 colours (4 bytes per patch) for the overlay, 2048 patches per row. */
  setOverlay(colours, patches) {
    const gl = this.gl;
    const rows = Math.max(1, Math.ceil(patches / 2048));
    const data = new Uint8Array(2048 * rows * 4);
    data.set(colours.subarray(0, Math.min(colours.length, data.length)));
    gl.bindTexture(gl.TEXTURE_2D, this.overlay);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, 2048, rows, 0, gl.RGBA, gl.UNSIGNED_BYTE, data);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  }

  resize() {
    const ratio = window.devicePixelRatio || 1;
    const width = Math.max(1, Math.round(this.canvas.clientWidth * ratio));
    const height = Math.max(1, Math.round(this.canvas.clientHeight * ratio));
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
  }

  draw(mesh, matrix, exposure, mode, target = null) {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, target);
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    if (mode === 2) gl.clearColor(0, 0, 0, 0); else gl.clearColor(0.02, 0.02, 0.025, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!mesh) return;
    gl.enable(gl.DEPTH_TEST);
    // Each side of a surface is its own patch, facing its own way: the back of a one-sided wall
    // is not drawn, so a closed room can be looked into from outside.
    gl.enable(gl.CULL_FACE);
    gl.useProgram(this.program);
    gl.uniformMatrix4fv(this.uniform.u_matrix, false, matrix);
    gl.uniform1f(this.uniform.u_exposure, exposure);
    gl.uniform1i(this.uniform.u_mode, mode);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.overlay);
    gl.uniform1i(this.uniform.u_overlay, 0);
    gl.bindVertexArray(mesh.vao);
    gl.drawArrays(gl.TRIANGLES, 0, mesh.count);
    gl.bindVertexArray(null);
  }

  /** The patch drawn at canvas pixel (x, y) from the top left, or null. */
  pick(mesh, matrix, x, y) {
    const gl = this.gl;
    const { width, height } = this.canvas;
    if (!this.pickTarget || this.pickTarget.width !== width || this.pickTarget.height !== height) {
      if (this.pickTarget) { gl.deleteFramebuffer(this.pickTarget.fb); gl.deleteRenderbuffer(this.pickTarget.colour); gl.deleteRenderbuffer(this.pickTarget.depth); }
      const fb = gl.createFramebuffer();
      const colour = gl.createRenderbuffer();
      const depth = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, colour);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA8, width, height);
      gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, colour);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
      this.pickTarget = { fb, colour, depth, width, height };
    }
    this.draw(mesh, matrix, 1, 2, this.pickTarget.fb);
    const pixel = new Uint8Array(4);
    gl.readPixels(x, height - 1 - y, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    const id = pixel[0] + pixel[1] * 256 + pixel[2] * 65536 + pixel[3] * 16777216;
    return id === 0 ? null : id - 1;
  }
}

// ---------------------------------------------------------------------------------------------
// False colours.

/** Viridis at t in [0, 1] (a few of its stops, interpolated), as 0–255 RGB. */
function viridis(t) {
  const stops = [[68, 1, 84], [65, 68, 135], [42, 120, 142], [34, 168, 132], [122, 209, 81], [253, 231, 37]];
  const x = Math.min(Math.max(t, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(x), stops.length - 2);
  const f = x - i;
  return stops[i].map((a, c) => Math.round(a + (stops[i + 1][c] - a) * f));
}
const UNSAMPLED = [255, 0, 255];
const UNLIT = [90, 90, 90];

/**
 * The overlay's colour per patch from a frame's binary solution, and its legend. Relative error:
 * the luminance of σ over the luminance of the radiance, 0 to 20 % (unlit patches grey);
 * samples: line crossings on a log scale to the most in the frame. Unsampled patches magenta.
 */
function overlayColours(kind, solution) {
  const { patches, radiance, stderr, samples } = solution;
  const colours = new Uint8Array(patches * 4);
  let most = 1;
  for (let p = 0; p < patches; p++) most = Math.max(most, samples[p]);
  for (let p = 0; p < patches; p++) {
    let c;
    if (samples[p] === 0) c = UNSAMPLED;
    else if (kind === 'samples') c = viridis(Math.log(samples[p]) / Math.log(most));
    else {
      const l = luminance(radiance.subarray(3 * p, 3 * p + 3));
      const s = luminance(stderr.subarray(3 * p, 3 * p + 3));
      c = l > 0 ? viridis(s / l / 0.2) : UNLIT;
    }
    colours.set([c[0], c[1], c[2], 255], 4 * p);
  }
  const legend = kind === 'samples'
    ? { title: 'line crossings per patch (log)', min: '1', max: String(most) }
    : { title: 'relative error σ / radiance', min: '0 %', max: '≥ 20 %' };
  return { colours, legend };
}

/** A frame's binary solution (GET …/frames/{f} with Accept: application/octet-stream). */
function parseSolution(buffer) {
  const view = new DataView(buffer);
  const patches = view.getUint32(4, true);
  return {
    patches,
    radiance: new Float32Array(buffer, 16, patches * 3),
    stderr: new Float32Array(buffer, 16 + patches * 12, patches * 3),
    samples: new Uint32Array(buffer, 16 + patches * 24, patches),
  };
}

// ---------------------------------------------------------------------------------------------
// Viewer.

class Viewer {
  constructor(id) {
    this.id = id;
    this.base = `/v1/timelines/${id}`;
    this.renderer = new Renderer($('canvas'));
    this.status = null;
    this.version = 0;
    this.frames = new Map(); // frame → { version, data, mesh, used }
    this.loading = new Map(); // frame → promise
    this.solutions = new Map(); // `${frame}/${version}` → solution
    this.frame = 0;
    this.shown = null; // the frame entry drawn
    this.playing = false;
    this.timelineExposure = null;
    this.orbit = null;
    this.view = 'orbit';
    this.overlay = 'none';
    this.picked = null;
    this.patchTable = null;
    this.materials = null;
    const params = new URLSearchParams(location.search);
    this.frame = Math.max(0, parseInt(params.get('frame') || '0', 10) || 0);
    const exposure = parseFloat(params.get('exposure'));
    this.exposure = exposure > 0 ? exposure : null;
    this.userExposure = this.exposure !== null;
    if (['error', 'samples'].includes(params.get('overlay'))) this.overlay = params.get('overlay');
    this.initialOrbit = (params.get('orbit') || '').split(',').map(parseFloat);
    $('overlay').value = this.overlay;
    window.viewer = this; // for tests and the curious: the state of the page
  }

  async start() {
    $('viewer').hidden = false;
    $('title').textContent = this.id;
    document.title = `radiosity · ${this.id}`;
    this.bindControls();
    new ResizeObserver(() => this.redraw()).observe($('canvas'));
    await this.refreshStatus();
    this.listen();
    this.loadMaterials();
  }

  bindControls() {
    $('frame').addEventListener('input', (e) => this.show(parseInt(e.target.value, 10)));
    $('play').addEventListener('click', () => this.togglePlay());
    document.addEventListener('keydown', (e) => {
      if (e.key === ' ' && e.target === document.body) { e.preventDefault(); this.togglePlay(); }
    });
    $('exposure').addEventListener('input', (e) => {
      if (!this.timelineExposure) return;
      this.exposure = this.timelineExposure * 2 ** parseFloat(e.target.value);
      this.userExposure = true;
      this.updateUrl();
      this.redraw();
    });
    $('view').addEventListener('change', (e) => { this.view = e.target.value; this.redraw(); });
    $('overlay').addEventListener('change', (e) => { this.overlay = e.target.value; this.updateUrl(); this.updateOverlay(); });
    const canvas = $('canvas');
    let drag = null;
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      drag = { x: e.clientX, y: e.clientY, startX: e.clientX, startY: e.clientY, pan: e.button !== 0 || e.shiftKey };
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag || !this.orbit) return;
      const dx = e.clientX - drag.x;
      const dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (this.view !== 'orbit') { this.view = 'orbit'; $('view').value = 'orbit'; }
      const o = this.orbit;
      if (drag.pan) {
        const [x, y] = this.orbitAxes();
        const k = (o.distance * 2 * Math.tan(o.yfov / 2)) / canvas.clientHeight;
        for (let a = 0; a < 3; a++) o.target[a] += (-dx * x[a] + dy * y[a]) * k;
      } else {
        o.yaw -= dx * 0.008;
        o.pitch = Math.min(1.55, Math.max(-1.55, o.pitch - dy * 0.008));
      }
      this.redraw();
    });
    canvas.addEventListener('pointerup', (e) => {
      if (drag && Math.hypot(e.clientX - drag.startX, e.clientY - drag.startY) < 4) this.pickAt(e);
      else if (drag && this.orbit) { this.orbitSet = true; this.updateUrl(); }
      drag = null;
    });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      if (!this.orbit) return;
      if (this.view !== 'orbit') { this.view = 'orbit'; $('view').value = 'orbit'; }
      this.orbit.distance *= Math.exp(e.deltaY * 0.001);
      this.orbitSet = true;
      this.updateUrl();
      this.redraw();
    }, { passive: false });
  }

  // --- status, progress and frames as they are solved

  async refreshStatus() {
    try {
      this.onStatus(await getJson(this.base));
    } catch (e) {
      this.message(e.message);
    }
  }

  /** Follows the job's events while it runs (the stream ends with the job). */
  listen() {
    if (this.events || !this.status || ['done', 'failed', 'cancelled'].includes(this.status.status)) return;
    const events = new EventSource(`${this.base}/events`);
    this.events = events;
    events.addEventListener('status', (e) => {
      const status = JSON.parse(e.data);
      this.onStatus(status);
      if (['done', 'failed', 'cancelled'].includes(status.status)) { events.close(); this.events = null; }
    });
    events.onerror = () => { events.close(); this.events = null; setTimeout(() => this.refreshStatus().then(() => this.listen()), 2000); };
  }

  onStatus(status) {
    const newVersion = status.version !== this.version;
    this.status = status;
    this.version = status.version;
    const frames = status.frames;
    $('frame').max = Math.max(0, frames - 1);
    if (this.frame >= frames) this.frame = Math.max(0, frames - 1);
    $('frame').value = this.frame;
    const p = status.progress;
    const running = !['done', 'failed', 'cancelled'].includes(status.status);
    $('progress').hidden = !running && status.status === 'done';
    let fraction = 0;
    let text = status.status;
    if (status.status === 'tracing' && p.lines_total) {
      fraction = p.lines_traced / p.lines_total;
      text = `tracing ${Math.round(fraction * 100)} %`;
    } else if (status.status === 'solving' || status.status === 'done') {
      fraction = p.frames_total ? p.frames_solved / p.frames_total : 1;
      text = `solving: ${p.frames_solved} of ${p.frames_total} frames`;
    }
    if (p.eta_seconds != null) text += `, ${fmt(p.eta_seconds, 2)} s left`;
    if (status.error) text += `: ${status.error}`;
    $('progress-bar').value = fraction;
    $('progress-text').textContent = text;
    document.body.dataset.status = status.status;
    if (!running) (this.finishWaiters || []).splice(0).forEach((resolve) => resolve());
    if (status.version > 1) $('relight-status').textContent = `version ${status.version}: ${status.status}`;
    if (newVersion) this.solutions.clear();
    const want = this.frames.get(this.frame);
    if (this.isReady(this.frame) && (!want || want.version !== this.version)) this.show(this.frame);
    else if (!this.shown) this.message(status.status === 'failed' ? `failed: ${status.error}` : `waiting for frame ${this.frame} (${text})`);
  }

  /** Whether `frame` is solved for the current result version. */
  isReady(frame) {
    return !!this.status && this.status.iterations[frame] != null;
  }

  /** Fetches frame `frame`'s glb (once at a time per frame) and keeps it, a few at most. */
  load(frame) {
    const kept = this.frames.get(frame);
    if (kept && kept.version === this.version) return Promise.resolve(kept);
    if (this.loading.has(frame)) return this.loading.get(frame);
    const promise = (async () => {
      // The frame's solution too: which side of each triangle is lit, for the cutaway.
      const [response, solution] = await Promise.all([
        request(`${this.base}/frames/${frame}/baked.glb`),
        this.solution(frame, this.version),
      ]);
      const version = parseInt(response.headers.get('x-result-version'), 10);
      const exposure = parseFloat(response.headers.get('x-exposure'));
      const { arrays, cut } = cutaway(frameFromGlb(await response.arrayBuffer()), solution);
      const mesh = this.renderer.upload(arrays);
      // The GPU has the vertices; the page keeps the rest.
      const data = { ...arrays, position: null, radiance: null, patch: null, cut };
      const entry = { frame, version, data, mesh, used: performance.now() };
      const old = this.frames.get(frame);
      if (old && old !== this.shown) old.mesh.release();
      this.frames.set(frame, entry);
      this.evict(data.corners * 28);
      // The timeline's exposure (from every frame solved so far), which the view follows
      // until the user sets one.
      this.timelineExposure = exposure;
      if (!this.userExposure) this.exposure = exposure;
      $('exposure').value = Math.log2(this.exposure / exposure);
      if (!this.orbit) this.frameScene(data);
      return entry;
    })().finally(() => this.loading.delete(frame));
    this.loading.set(frame, promise);
    return promise;
  }

  /** Keeps the frames' GPU memory under about 256 MB, dropping the least recently shown. */
  evict(bytesPerFrame) {
    const keep = Math.max(3, Math.floor(256e6 / Math.max(1, bytesPerFrame)));
    const entries = [...this.frames.values()].sort((a, b) => a.used - b.used);
    while (entries.length > keep) {
      const e = entries.shift();
      if (e === this.shown) continue;
      e.mesh.release();
      this.frames.delete(e.frame);
    }
  }

  /** Shows frame `frame` when it is solved (the latest shown stays until then). */
  async show(frame) {
    this.frame = frame;
    $('frame').value = frame;
    $('frame-label').textContent = `frame ${frame} of ${this.status ? this.status.frames - 1 : '?'}`;
    this.updateUrl();
    if (!this.isReady(frame)) { this.message(`frame ${frame} is not solved yet`); return; }
    try {
      const entry = await this.load(frame);
      if (this.frame !== frame) return;
      entry.used = performance.now();
      this.shown = entry;
      $('frame-time').textContent = entry.data.time != null ? `t = ${fmt(entry.data.time, 4)} s` : '';
      this.message('');
      this.updateUrl();
      await this.updateOverlay();
      this.redraw();
      this.showPick();
    } catch (e) {
      this.message(`frame ${frame}: ${e.message}`);
    }
  }

  togglePlay() {
    this.playing = !this.playing;
    $('play').textContent = this.playing ? '❚❚' : '▶';
    if (this.playing) this.play();
  }

  /** Steps through the solved frames at the timeline's rate, waiting for any not yet loaded. */
  async play() {
    if (this.playLoop) return;
    this.playLoop = true;
    try {
      await this.playFrames();
    } finally {
      this.playLoop = false;
    }
  }

  async playFrames() {
    while (this.playing && this.status) {
      const started = performance.now();
      const frames = this.status.frames;
      let next = (this.frame + 1) % frames;
      for (let k = 0; k < frames && !this.isReady(next); k++) next = (next + 1) % frames;
      if (!this.isReady(next)) break;
      await this.show(next);
      for (let k = 1; k <= 2; k++) if (this.isReady((next + k) % frames)) this.load((next + k) % frames).catch(() => {});
      const wait = 1000 / this.fps() - (performance.now() - started);
      await new Promise((r) => setTimeout(r, Math.max(0, wait)));
    }
  }

  /** Frames per second, from the times of two loaded frames (24 until two are). */
  fps() {
    const loaded = [...this.frames.values()].filter((e) => e.data.time != null);
    for (let i = 1; i < loaded.length; i++) {
      const a = loaded[0];
      const b = loaded[i];
      if (a.frame !== b.frame && b.data.time !== a.data.time) return Math.min(120, Math.abs((b.frame - a.frame) / (b.data.time - a.data.time)));
    }
    return 24;
  }

  updateUrl() {
    const params = new URLSearchParams({ frame: this.frame });
    if (this.exposure) params.set('exposure', fmt(this.exposure, 4));
    if (this.overlay !== 'none') params.set('overlay', this.overlay);
    if (this.orbitSet && this.view === 'orbit') {
      const o = this.orbit;
      const degrees = (a) => fmt((a * 180) / Math.PI, 4);
      params.set('orbit', `${degrees(o.yaw)},${degrees(o.pitch)},${fmt(o.distance / o.framing, 3)}`);
    }
    history.replaceState(null, '', `?${params}`);
    $('exposure-label').textContent = this.exposure ? `× ${fmt(this.exposure, 3)}${this.timelineExposure ? ` (timeline’s × ${fmt(this.timelineExposure, 3)})` : ''}` : '';
  }

  message(text) { $('stage-message').textContent = text; }

  // --- camera

  frameScene(data) {
    const centre = data.min.map((m, a) => (m + data.max[a]) / 2);
    const radius = Math.max(1e-9, Math.hypot(...data.max.map((m, a) => m - data.min[a])) / 2);
    const framing = (radius / Math.sin((50 * Math.PI) / 360)) * 1.05;
    this.orbit = { target: centre, radius, framing, distance: framing, yaw: Math.atan2(0.6, 0.9), pitch: Math.asin(0.45 / Math.hypot(0.6, 0.45, 0.9)), yfov: (50 * Math.PI) / 180 };
    // ?orbit=yaw,pitch,zoom (degrees, degrees, distance over the framing one) sets the view.
    const orbit = this.initialOrbit;
    if (orbit.length === 3 && orbit.every(Number.isFinite) && orbit[2] > 0) {
      this.orbit.yaw = (orbit[0] * Math.PI) / 180;
      this.orbit.pitch = Math.min(89, Math.max(-89, orbit[1])) * Math.PI / 180;
      this.orbit.distance = framing * orbit[2];
      this.orbitSet = true;
    }
    const select = $('view');
    for (const [i, c] of data.cameras.entries()) select.append(element('option', { value: `camera${i}`, textContent: `camera: ${c.name}` }));
    if (data.cameras.length && !this.orbitSet) {
      this.view = 'camera0';
      select.value = 'camera0';
    }
  }

  /** The orbit camera's right, up and backward axes. */
  orbitAxes() {
    const { yaw, pitch } = this.orbit;
    const z = [Math.sin(yaw) * Math.cos(pitch), Math.sin(pitch), Math.cos(yaw) * Math.cos(pitch)];
    const x = [Math.cos(yaw), 0, -Math.sin(yaw)];
    const y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
    return [x, y, z];
  }

  matrix() {
    const canvas = this.renderer.canvas;
    const aspect = canvas.width / canvas.height;
    const cameras = this.shown ? this.shown.data.cameras : [];
    const camera = this.view.startsWith('camera') ? cameras[parseInt(this.view.slice(6), 10)] : null;
    if (camera) {
      const [x, y, z] = quaternionAxes(camera.rotation);
      const view = mat4.view(camera.translation, x, y, z);
      const p = camera.projection;
      const projection = p.type === 'orthographic'
        ? mat4.orthographic(p.orthographic.ymag * aspect, p.orthographic.ymag, p.orthographic.znear, p.orthographic.zfar)
        : mat4.perspective(p.perspective.yfov, aspect, p.perspective.znear, p.perspective.zfar);
      return mat4.multiply(projection, view);
    }
    const o = this.orbit;
    const [x, y, z] = this.orbitAxes();
    const eye = o.target.map((t, a) => t + z[a] * o.distance);
    const near = Math.max(o.distance - 2 * o.radius, o.distance * 1e-3, o.radius * 1e-4);
    const projection = mat4.perspective(o.yfov, aspect, near, o.distance + 2 * o.radius);
    return mat4.multiply(projection, mat4.view(eye, x, y, z));
  }

  /** Where the point `p` (scene units) is drawn, in CSS pixels from the page's top left. */
  project(p) {
    const m = this.matrix();
    const q = p.map((x, a) => x - this.shown.data.origin[a]);
    const clip = [0, 1, 2, 3].map((r) => m[r] * q[0] + m[4 + r] * q[1] + m[8 + r] * q[2] + m[12 + r]);
    const rect = this.renderer.canvas.getBoundingClientRect();
    return [rect.left + ((clip[0] / clip[3] + 1) / 2) * rect.width, rect.top + ((1 - clip[1] / clip[3]) / 2) * rect.height];
  }

  redraw() {
    if (this.drawPending) return;
    this.drawPending = true;
    requestAnimationFrame(() => {
      this.drawPending = false;
      this.renderer.resize();
      if (!this.shown || !this.orbit) { this.renderer.draw(null); return; }
      const mode = this.overlay !== 'none' && this.overlayReady ? 1 : 0;
      this.renderer.draw(this.shown.mesh, this.matrix(), this.exposure || 1, mode);
      document.body.dataset.frame = this.shown.frame;
      document.body.dataset.version = this.shown.version;
      document.body.dataset.mode = mode ? this.overlay : 'light';
      document.body.dataset.draws = (parseInt(document.body.dataset.draws || '0', 10) + 1).toString();
    });
  }

  // --- error and sample overlays, picking

  /** The shown frame's solution (radiance, σ, samples per patch), fetched once per version. */
  async solution(frame, version) {
    const key = `${frame}/${version}`;
    if (!this.solutions.has(key)) {
      const response = await request(`${this.base}/frames/${frame}`, { headers: { accept: 'application/octet-stream' } });
      if (this.solutions.size > 8) this.solutions.delete(this.solutions.keys().next().value);
      this.solutions.set(key, parseSolution(await response.arrayBuffer()));
    }
    return this.solutions.get(key);
  }

  async updateOverlay() {
    this.overlayReady = false;
    $('legend').hidden = true;
    if (this.overlay !== 'none' && this.shown) {
      const shown = this.shown;
      const solution = await this.solution(shown.frame, shown.version);
      if (shown !== this.shown) return;
      const { colours, legend } = overlayColours(this.overlay, solution);
      this.renderer.setOverlay(colours, solution.patches);
      $('legend-bar').style.background = `linear-gradient(to right, ${[0, 0.2, 0.4, 0.6, 0.8, 1].map((t) => `rgb(${viridis(t)})`).join(', ')})`;
      $('legend-title').textContent = legend.title;
      $('legend-min').textContent = legend.min;
      $('legend-max').textContent = legend.max;
      $('legend').hidden = false;
      this.overlayReady = true;
    }
    this.redraw();
  }

  pickAt(e) {
    if (!this.shown || !this.orbit) return;
    const canvas = this.renderer.canvas;
    const rect = canvas.getBoundingClientRect();
    const x = Math.floor(((e.clientX - rect.left) / rect.width) * canvas.width);
    const y = Math.floor(((e.clientY - rect.top) / rect.height) * canvas.height);
    this.renderer.resize();
    this.picked = this.renderer.pick(this.shown.mesh, this.matrix(), x, y);
    this.redraw();
    this.showPick();
  }

  async showPick() {
    const patch = this.picked;
    const info = $('pick-info');
    if (patch == null || !this.shown) { info.textContent = 'Click a surface.'; return; }
    const shown = this.shown;
    try {
      const [solution, table, lighting] = await Promise.all([
        this.solution(shown.frame, shown.version),
        this.patchTable || (this.patchTable = getJson(`${this.base}/patches`)),
        this.materials || (this.materials = getJson(`${this.base}/materials`)),
      ]);
      const row = (table.patches || [])[patch] || {};
      const material = lighting.materials[row.material];
      const sampled = solution.samples[patch] > 0;
      const L = solution.radiance.subarray(3 * patch, 3 * patch + 3);
      const s = solution.stderr.subarray(3 * patch, 3 * patch + 3);
      const entries = [
        ['patch', `${patch}${row.side ? ` (${row.side})` : ''}`],
        ['node', `${shown.data.nodeOfPatch.get(patch) ?? '–'} (${row.node ?? '–'})`],
        ['material', material ? `${material.name ?? 'unnamed'} (${material.index})` : '–'],
        ['radiance', rgb(L)],
        ['σ', sampled ? rgb(s) : 'not sampled'],
        ['σ / radiance', sampled && luminance(L) > 0 ? `${fmt((100 * luminance(s)) / luminance(L), 2)} %` : '–'],
        ['samples', String(solution.samples[patch])],
        ['frame', `${shown.frame} (version ${shown.version})`],
      ];
      info.replaceChildren(element('dl', {}, entries.flatMap(([k, v]) => [element('dt', { textContent: k }), element('dd', { textContent: v })])));
      info.dataset.patch = patch;
    } catch (e) {
      info.textContent = e.message;
    }
  }

  // --- relighting

  /** Sliders for each emitting material's strength and each light's intensity. */
  async loadMaterials() {
    let lighting;
    try {
      lighting = await (this.materials = getJson(`${this.base}/materials`));
    } catch (_) { return; }
    this.wanted = { materials: new Map(), lights: new Map() };
    const controls = $('relight-controls');
    controls.replaceChildren();
    const slider = (label, change) => {
      const input = element('input', { type: 'range', min: '-4', max: '4', step: '0.25', value: '0' });
      const value = element('span', { textContent: '× 1' });
      input.setAttribute('aria-label', label);
      input.addEventListener('input', () => { value.textContent = `× ${fmt(2 ** parseFloat(input.value))}`; });
      input.addEventListener('change', () => change(2 ** parseFloat(input.value)));
      controls.append(element('label', { textContent: `${label} ` }, [value, input]));
    };
    for (const m of lighting.materials.filter((m) => m.emission.some((e) => e > 0))) {
      slider(`emission of ${m.name ?? `material ${m.index}`}`, (k) => this.relight('materials', m.index, { material: m.index, emission: m.emission.map((e) => e * k) }));
    }
    for (const l of lighting.lights) {
      slider(`intensity of ${l.name ?? `light ${l.index}`}`, (k) => this.relight('lights', l.index, { light: l.index, intensity: l.intensity * k }));
    }
    $('relight').hidden = controls.childElementCount === 0;
  }

  /**
   * Asks for `change` of a material or light. Changes made while a relight runs are sent
   * together once it is done: what is solved last is what the sliders show.
   */
  relight(kind, index, change) {
    this.wanted[kind].set(index, change);
    this.relightDirty = true;
    // The exposure stays where it is, so the change shows (the timeline's own follows the
    // light's level).
    this.userExposure = this.exposure !== null;
    if (!this.relighting) this.sendRelight();
  }

  async sendRelight() {
    this.relighting = true;
    for (let attempt = 0; this.relightDirty && attempt < 100; attempt++) {
      await this.untilFinished();
      this.relightDirty = false;
      const body = { materials: [...this.wanted.materials.values()], lights: [...this.wanted.lights.values()] };
      $('relight-status').textContent = 'relighting…';
      try {
        const response = await request(`${this.base}/materials`, { method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify(body) });
        const rerun = await response.json();
        $('relight-status').textContent = `version ${rerun.version}: ${rerun.status}`;
      } catch (e) {
        $('relight-status').textContent = e.message;
        if (e.status !== 409) break;
        this.relightDirty = true; // busy: again once it is done
        await new Promise((r) => setTimeout(r, 200));
      }
      await this.refreshStatus();
      this.listen();
    }
    this.relighting = false;
  }

  /** Resolves once the job is done, failed or cancelled. */
  untilFinished() {
    if (!this.status || ['done', 'failed', 'cancelled'].includes(this.status.status)) return Promise.resolve();
    return new Promise((resolve) => (this.finishWaiters = [...(this.finishWaiters || []), resolve]));
  }
}

// ---------------------------------------------------------------------------------------------

const match = location.pathname.match(/^\/v1\/timelines\/([^/]+)\/viewer\/?$/);
if (match) {
  try {
    new Viewer(decodeURIComponent(match[1])).start();
  } catch (e) {
    $('viewer').hidden = false;
    $('stage-message').textContent = e.message;
  }
} else {
  home();
}
