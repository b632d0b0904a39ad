// The service's lightmaps and light probes in three.js: an example page, and what it shows of
// how an engine loads them (docs/import.md walks through it).
//
// - The geometry: `lightmap.glb` (GLTFLoader): every node on the lightmap's vertices, the atlas
//   coordinates in TEXCOORD_1 (three.js's `uv1`), a primitive per material (its albedo and
//   emission), rigid moving nodes animated by the "baked motion" clip at the frames' times.
// - The lightmaps: `lightmap.json?quantity=light` lists every frame's time and lighting state;
//   each state's EXR (EXRLoader) is loaded once and shown on every static node as `lightMap`
//   on channel 1. Its texels are the light (the irradiance over π, albedo-free), so a
//   material shows albedo × light + emission: three.js's `lightMap` at an intensity of π
//   (three.js divides a light map by π), the material's colour and emissive from the file.
// - The probes: a state's `probes.json` (SH L2 of the arriving radiance, per probe of a grid);
//   a moving node is lit from the probes around its centre, interpolated trilinearly, by a
//   shader that evaluates E(n) = Σ A_l L_lm Y_lm(n) and shows albedo × E / π.
// - The tone curve of the service's other outputs (x / (1 + Y(x)), x = exposure × radiance)
//   as three.js's custom tone mapping, then sRGB.
//
// ?frame=N opens at frame N; ?orbit=yaw,pitch,zoom as in the viewer; ?exposure=E;
// ?texels_per_unit=T and ?probe_spacing=S are passed on to the service.

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { EXRLoader } from 'three/addons/loaders/EXRLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const id = location.pathname.split('/')[3];
const base = `/v1/timelines/${id}`;
const density = params.get('texels_per_unit');
const lightmapQuery = `?quantity=light${density ? `&texels_per_unit=${encodeURIComponent(density)}` : ''}`;
const spacing = params.get('probe_spacing');
const probesQuery = spacing ? `?spacing=${encodeURIComponent(spacing)}` : '';

// The service's tone curve (its baked glTF's COLOR_0 and its previews use the same).
THREE.ShaderChunk.tonemapping_pars_fragment = THREE.ShaderChunk.tonemapping_pars_fragment.replace(
  'vec3 CustomToneMapping( vec3 color ) { return color; }',
  `vec3 CustomToneMapping( vec3 color ) {
    vec3 x = max( toneMappingExposure * color, 0.0 );
    float y = dot( x, vec3( 0.2126, 0.7152, 0.0722 ) );
    return clamp( x / ( 1.0 + y ), 0.0, 1.0 );
  }`,
);

// Irradiance from the probes' coefficients (the convention `probes.json` states: Godot's order
// 1; y, z, x; xy, yz, 3z²−1, xz, x²−y²; orthonormal real SH of the arriving radiance), times
// albedo / π.
const probeVertex = `
varying vec3 vNormal;
void main() {
  vNormal = normalize( mat3( modelMatrix ) * normal );
  gl_Position = projectionMatrix * modelViewMatrix * vec4( position, 1.0 );
}`;
const probeFragment = `
uniform vec3 sh[ 9 ];
uniform vec3 albedo;
varying vec3 vNormal;
void main() {
  vec3 n = normalize( vNormal );
  vec3 e = 3.14159265 * 0.2820948 * sh[ 0 ]
    + 2.0943951 * 0.4886025 * ( sh[ 1 ] * n.y + sh[ 2 ] * n.z + sh[ 3 ] * n.x )
    + 0.78539816 * ( 1.0925484 * ( sh[ 4 ] * n.x * n.y + sh[ 5 ] * n.y * n.z + sh[ 7 ] * n.x * n.z )
      + 0.3153916 * sh[ 6 ] * ( 3.0 * n.z * n.z - 1.0 )
      + 0.5462742 * sh[ 8 ] * ( n.x * n.x - n.y * n.y ) );
  gl_FragColor = vec4( albedo * max( e, 0.0 ) / 3.14159265, 1.0 );
  #include <tonemapping_fragment>
  #include <colorspace_fragment>
}`;

class Lightmapped {
  constructor() {
    this.canvas = $('canvas');
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.toneMapping = THREE.CustomToneMapping;
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.01, 100);
    this.states = new Map(); // state → promise of { lightmap, probes, exposure }
    this.lit = []; // static meshes' materials, which show the state's lightmap
    this.probeLit = []; // moving meshes and their materials' SH uniforms
    this.frame = -1;
    this.pending = 0;
  }

  async start() {
    const manifest = await this.json(`${base}/lightmap.json${lightmapQuery}`);
    this.frames = manifest.frames;
    const gltf = await new GLTFLoader().loadAsync(manifest.geometry);
    this.scene.add(gltf.scene);
    gltf.scene.traverse((object) => {
      if (!object.isMesh) return;
      // The node's extras are on the mesh, or on the group of its primitives.
      const node = object.userData.source_node === undefined ? object.parent : object;
      const { color, emissive, emissiveIntensity } = object.material;
      const glowing = emissive.r + emissive.g + emissive.b > 0;
      if (node.userData.moving === 'rigid' && !glowing) {
        const uniforms = {
          sh: { value: Array.from({ length: 9 }, () => new THREE.Vector3()) },
          albedo: { value: color.clone() },
        };
        object.material = new THREE.ShaderMaterial({ uniforms, vertexShader: probeVertex, fragmentShader: probeFragment });
        this.probeLit.push({ object: node, sh: uniforms.sh.value });
      } else {
        // No light objects in the scene: a Lambert material shows its lightmap and emission.
        object.material = new THREE.MeshLambertMaterial({ color, emissive, emissiveIntensity, lightMapIntensity: Math.PI });
        this.lit.push(object.material);
      }
    });
    this.mixer = new THREE.AnimationMixer(gltf.scene);
    for (const clip of gltf.animations) {
      const action = this.mixer.clipAction(clip);
      action.setLoop(THREE.LoopOnce);
      action.clampWhenFinished = true;
      action.play();
    }
    this.frameScene(gltf.scene);
    const slider = $('frame');
    slider.max = String(this.frames.length - 1);
    slider.addEventListener('input', () => this.show(parseInt(slider.value, 10)));
    $('play').addEventListener('click', () => this.play());
    window.addEventListener('resize', () => this.render());
    const first = Math.min(Math.max(parseInt(params.get('frame') || '0', 10) || 0, 0), this.frames.length - 1);
    slider.value = String(first);
    await this.show(first);
  }

  async json(url) {
    const response = await fetch(url);
    if (!response.ok) throw new Error(`${url}: ${response.status} ${await response.text()}`);
    return response.json();
  }

  /** A lighting state's lightmap (EXR) and probes, loaded once. */
  state(entry) {
    if (!this.states.has(entry.state)) {
      this.states.set(entry.state, (async () => {
        const response = await fetch(entry.lightmap);
        if (!response.ok) throw new Error(`${entry.lightmap}: ${response.status} ${await response.text()}`);
        const exposure = parseFloat(response.headers.get('x-exposure'));
        const data = new EXRLoader().parse(await response.arrayBuffer());
        const lightmap = new THREE.DataTexture(data.data, data.width, data.height, data.format, data.type);
        lightmap.colorSpace = THREE.LinearSRGBColorSpace;
        lightmap.magFilter = THREE.LinearFilter;
        lightmap.minFilter = THREE.LinearFilter;
        lightmap.generateMipmaps = false;
        lightmap.channel = 1;
        // EXRLoader stores the rows bottom first; glTF's v runs from the image's top.
        lightmap.repeat.set(1, -1);
        lightmap.offset.set(0, 1);
        lightmap.needsUpdate = true;
        const probes = await this.json(`${base}/frames/${entry.state}/probes.json${probesQuery}`);
        return { lightmap, probes, exposure };
      })());
    }
    return this.states.get(entry.state);
  }

  /** Shows frame `f` once its state is loaded (a later call wins). */
  async show(f) {
    const ticket = ++this.pending;
    const entry = this.frames[f];
    let state;
    try {
      state = await this.state(entry);
    } catch (error) {
      $('message').textContent = String(error.message || error);
      throw error;
    }
    if (ticket !== this.pending) return;
    for (const material of this.lit) {
      material.lightMap = state.lightmap;
      material.needsUpdate = true;
    }
    const exposure = parseFloat(params.get('exposure'));
    this.renderer.toneMappingExposure = exposure > 0 ? exposure : (state.exposure > 0 ? state.exposure : 1);
    this.mixer.setTime(entry.time - Math.min(this.frames[0].time, 0));
    this.scene.updateMatrixWorld(true);
    for (const { object, sh } of this.probeLit) {
      const centre = new THREE.Box3().setFromObject(object).getCenter(new THREE.Vector3());
      this.probesAt(state.probes, centre, sh);
    }
    this.frame = f;
    $('label').textContent = `frame ${f} · ${entry.time.toFixed(3)} s · lighting state ${entry.state}`;
    this.render();
    await new Promise((resolve) => requestAnimationFrame(resolve));
    if (ticket === this.pending) document.body.dataset.frame = String(f);
  }

  /** The probes' coefficients at `p`, trilinear over the grid's cell around it (probes
   * dropped inside static geometry left out, the weights renormalised), into `out`. */
  probesAt(probes, p, out) {
    const { origin, step, counts, indices } = probes;
    // The grid is the same at every state: where each grid index is among the probes kept.
    const slot = this.slots || (this.slots = new Map(indices.map((index, s) => [index, s])));
    const g = [p.x, p.y, p.z].map((x, a) => Math.min(Math.max((x - origin[a]) / step[a], 0), counts[a] - 1));
    const i0 = g.map((x, a) => Math.min(Math.floor(x), Math.max(counts[a] - 2, 0)));
    const t = g.map((x, a) => x - i0[a]);
    for (const v of out) v.set(0, 0, 0);
    let total = 0;
    for (let corner = 0; corner < 8; corner += 1) {
      const c = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
      const at = c.map((d, a) => Math.min(i0[a] + d, counts[a] - 1));
      const s = slot.get(at[0] + counts[0] * (at[1] + counts[1] * at[2]));
      if (s === undefined) continue;
      const w = c.reduce((product, d, a) => product * (d ? t[a] : 1 - t[a]), 1);
      if (w <= 0) continue;
      total += w;
      for (let m = 0; m < 9; m += 1) {
        const k = 27 * s + 3 * m;
        out[m].x += w * probes.sh[k];
        out[m].y += w * probes.sh[k + 1];
        out[m].z += w * probes.sh[k + 2];
      }
    }
    if (total > 0) {
      for (const v of out) v.multiplyScalar(1 / total);
    }
  }

  /** The viewer's automatic orbit (and its ?orbit=yaw,pitch,zoom), with OrbitControls. */
  frameScene(object) {
    const box = new THREE.Box3().setFromObject(object);
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(1e-9, box.getSize(new THREE.Vector3()).length() / 2);
    const framing = (radius / Math.sin((50 * Math.PI) / 360)) * 1.05;
    let [yaw, pitch, distance] = [Math.atan2(0.6, 0.9), Math.asin(0.45 / Math.hypot(0.6, 0.45, 0.9)), framing];
    const orbit = (params.get('orbit') || '').split(',').map(parseFloat);
    if (orbit.length === 3 && orbit.every(Number.isFinite) && orbit[2] > 0) {
      yaw = (orbit[0] * Math.PI) / 180;
      pitch = (Math.min(89, Math.max(-89, orbit[1])) * Math.PI) / 180;
      distance = framing * orbit[2];
    }
    const z = new THREE.Vector3(Math.sin(yaw) * Math.cos(pitch), Math.sin(pitch), Math.cos(yaw) * Math.cos(pitch));
    this.camera.position.copy(centre).addScaledVector(z, distance);
    this.camera.near = Math.max(distance - 2 * radius, distance * 1e-3, radius * 1e-4);
    this.camera.far = distance + 2 * radius;
    this.camera.lookAt(centre);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.target.copy(centre);
    this.controls.update();
    this.controls.addEventListener('change', () => this.render());
  }

  render() {
    const width = this.canvas.clientWidth;
    const height = this.canvas.clientHeight;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / Math.max(height, 1);
    this.camera.updateProjectionMatrix();
    this.renderer.render(this.scene, this.camera);
  }

  /** Where the point `p` (scene units) is drawn, in CSS pixels from the page's top left. */
  project(p) {
    const v = new THREE.Vector3(...p).project(this.camera);
    const rect = this.canvas.getBoundingClientRect();
    return [rect.left + ((v.x + 1) / 2) * rect.width, rect.top + ((1 - v.y) / 2) * rect.height];
  }

  async play() {
    for (let f = this.frame + 1; f < this.frames.length; f += 1) {
      $('frame').value = String(f);
      await this.show(f);
      const next = this.frames[f + 1];
      if (next) await new Promise((resolve) => setTimeout(resolve, 1000 * (next.time - this.frames[f].time)));
    }
  }
}

const page = new Lightmapped();
window.lightmapped = page;
page.start().catch((error) => {
  $('message').textContent = String(error.message || error);
  console.error(error);
});
