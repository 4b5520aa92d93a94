import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import URDFLoader, { type URDFRobot } from "urdf-loader";
import { num, type StateMessage } from "./types";

/** The arm's joints as the URDF (`GET /api/robot.urdf`) names them. */
export const JOINT_NAMES = ["A1", "A2", "A3", "A4", "A5", "A6", "A7"] as const;

/** Lab geometry the twin needs from `GET /api/params`. */
export interface TwinGeometry {
  length_m: number;
  intercept_height_m: number;
  home_m: [number, number, number];
  tool_length_m: number;
  ball_radius_m: number;
}

export const DEFAULT_GEOMETRY: TwinGeometry = {
  length_m: 1.93,
  intercept_height_m: 0.3,
  home_m: [0.3, 0, 0.5],
  tool_length_m: 0.1,
  ball_radius_m: 0.0335,
};

const up = new THREE.Vector3(0, 1, 0);

/** Places a unit cylinder (height 1 along y) between two points. */
function stretch(mesh: THREE.Mesh, a: THREE.Vector3, b: THREE.Vector3): void {
  const d = b.clone().sub(a);
  const len = d.length();
  mesh.visible = len > 1e-6;
  if (!mesh.visible) return;
  mesh.position.copy(a).addScaledVector(d, 0.5);
  mesh.scale.set(1, len, 1);
  mesh.quaternion.setFromUnitVectors(up, d.divideScalar(len));
}

/** What `Twin.probe` reports: a link as drawn, for the browser test. */
export interface LinkProbe {
  name: string;
  /** Link origin, base frame, metres (from the drawn scene graph). */
  world: [number, number, number];
  /** Where it lands on the canvas, CSS pixels from the top left. */
  screen: [number, number];
  /** The rendered pixel there (RGBA 0..255). */
  rgba: [number, number, number, number];
}

/** The 3D twin: the iiwa 7 from its URDF (urdf-loader), pendulum, ball, prediction, intercept and tool path. */
export class Twin {
  readonly renderer: THREE.WebGLRenderer | null;
  private readonly scene = new THREE.Scene();
  private readonly camera: THREE.PerspectiveCamera;
  private readonly controls: OrbitControls | null;
  private robot: URDFRobot | null = null;
  private q: number[] = [0, 0.5, 0, -1.4, 0, 1.2, 0];
  private readonly ball: THREE.Mesh;
  private readonly truth: THREE.Mesh;
  private readonly string: THREE.Mesh;
  private readonly intercept: THREE.Mesh;
  private readonly predicted: THREE.Line;
  private readonly toolPath: THREE.Line;
  private latest: StateMessage | null = null;
  private dirty = true;
  private renderedAt = Number.NEGATIVE_INFINITY;
  private readonly shown: Shown = new Float64Array(SHOWN_LEN).fill(Number.NaN);
  geometry: TwinGeometry = DEFAULT_GEOMETRY;
  /** Frames rendered (the browser test checks the view renders). */
  frames = 0;

  constructor(private readonly host: HTMLElement) {
    let renderer: THREE.WebGLRenderer | null = null;
    try {
      // Multisampling on a software renderer (SwiftShader: no GPU) costs the page a
      // third of its frames; edges there stay aliased.
      renderer = new THREE.WebGLRenderer({ antialias: !softwareWebGl() });
    } catch {
      host.textContent = "3D view unavailable (no WebGL in this browser)";
    }
    this.renderer = renderer;
    this.scene.background = new THREE.Color("#f4f6f8");
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.01, 50);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(-0.9, -1.7, 1.2);
    this.scene.add(new THREE.HemisphereLight("#ffffff", "#8899aa", 2.2));
    const sun = new THREE.DirectionalLight("#ffffff", 1.5);
    sun.position.set(2, -2, 4);
    this.scene.add(sun);
    const grid = new THREE.GridHelper(3, 30, "#99a", "#ccd");
    grid.rotation.x = Math.PI / 2;
    this.scene.add(grid);
    this.scene.add(new THREE.AxesHelper(0.25));

    const ballMat = new THREE.MeshStandardMaterial({ color: "#c8e03c", roughness: 0.8 });
    this.ball = new THREE.Mesh(new THREE.SphereGeometry(1, 24, 16), ballMat);
    this.truth = new THREE.Mesh(
      new THREE.SphereGeometry(1, 16, 12),
      new THREE.MeshBasicMaterial({ color: "#0072B2", wireframe: true }),
    );
    this.string = new THREE.Mesh(new THREE.CylinderGeometry(0.003, 0.003, 1, 6), new THREE.MeshBasicMaterial({ color: "#444" }));
    this.intercept = new THREE.Mesh(
      new THREE.TorusGeometry(0.05, 0.006, 8, 32),
      new THREE.MeshBasicMaterial({ color: "#009E73" }),
    );
    this.intercept.rotation.y = Math.PI / 2;
    this.predicted = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineDashedMaterial({ color: "#0072B2", dashSize: 0.03, gapSize: 0.02 }));
    this.predicted.geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(3 * 64), 3));
    this.toolPath = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: "#D55E00" }));
    this.toolPath.geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(6), 3));
    this.scene.add(this.ball, this.truth, this.string, this.intercept, this.predicted, this.toolPath);

    if (renderer) {
      host.append(renderer.domElement);
      renderer.domElement.setAttribute("aria-label", "3D view of the arm and the pendulum");
      renderer.domElement.tabIndex = 0;
      this.controls = new OrbitControls(this.camera, renderer.domElement);
      this.controls.target.set(0.45, 0, 0.5);
      this.controls.addEventListener("change", () => (this.dirty = true));
      this.controls.update();
      new ResizeObserver(() => this.resize()).observe(host);
      this.resize();
    } else {
      this.controls = null;
    }
  }

  /** Loads the arm from its URDF (the server's, with the tool length in effect). */
  async loadRobot(url = "/api/robot.urdf"): Promise<void> {
    const r = await fetch(url);
    if (!r.ok) throw new Error(`GET ${url}: ${r.status}`);
    const robot = new URDFLoader().parse(await r.text());
    if (this.robot) this.scene.remove(this.robot);
    this.robot = robot;
    this.scene.add(robot);
    this.pose(this.q);
    this.dirty = true;
  }

  /** True once the URDF arm is in the scene. */
  get robotLoaded(): boolean {
    return this.robot !== null;
  }

  private resize(): void {
    if (!this.renderer) return;
    const w = Math.max(200, this.host.clientWidth), h = Math.max(200, this.host.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  private pose(q: readonly number[]): void {
    this.q = [...q];
    if (!this.robot) return;
    for (let i = 0; i < JOINT_NAMES.length; i++) this.robot.setJointValue(JOINT_NAMES[i], q[i]);
    this.robot.updateMatrixWorld(true);
  }

  /**
   * Renders now and reports where the named links' origins are drawn and the
   * rendered pixel there (the browser test compares them with forward
   * kinematics projected through `view()`), with the joint angles drawn.
   */
  probe(names: readonly string[]): { q: number[]; links: LinkProbe[] } | null {
    const renderer = this.renderer;
    if (!renderer || !this.robot) return null;
    this.dirty = true;
    this.draw(Number.POSITIVE_INFINITY);
    const canvas = renderer.domElement;
    const gl = renderer.getContext();
    const links: LinkProbe[] = [];
    for (const name of names) {
      const link = this.robot.links[name];
      if (!link) continue;
      const w = new THREE.Vector3().setFromMatrixPosition(link.matrixWorld);
      const ndc = w.clone().project(this.camera);
      const sx = ((ndc.x + 1) / 2) * canvas.clientWidth;
      const sy = ((1 - ndc.y) / 2) * canvas.clientHeight;
      const bx = Math.round((sx / canvas.clientWidth) * gl.drawingBufferWidth);
      const by = Math.round((1 - sy / canvas.clientHeight) * gl.drawingBufferHeight);
      const px = new Uint8Array(4);
      gl.readPixels(bx, by, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      links.push({ name, world: [w.x, w.y, w.z], screen: [sx, sy], rgba: [px[0], px[1], px[2], px[3]] });
    }
    return { q: [...this.q], links };
  }

  /** The view: projection and world-to-camera matrices (column-major) and the canvas size in CSS pixels. */
  view(): { projection: number[]; worldToCamera: number[]; width: number; height: number } {
    this.camera.updateMatrixWorld();
    const c = this.renderer?.domElement;
    return {
      projection: this.camera.projectionMatrix.toArray(),
      worldToCamera: this.camera.matrixWorldInverse.toArray(),
      width: c?.clientWidth ?? 0,
      height: c?.clientHeight ?? 0,
    };
  }

  update(s: StateMessage): void {
    this.latest = s;
    // Software-rendered WebGL is the page's dearest paint: render only when
    // something visible moved (a still arm and a ball at rest cost nothing).
    if (!this.dirty && changed(this.shown, s)) this.dirty = true;
  }

  /** Renders if anything changed (at least once a second); call once per animation frame. */
  draw(now = performance.now()): void {
    if (!this.renderer || (!this.dirty && now - this.renderedAt < 1000)) return;
    this.dirty = false;
    this.renderedAt = now;
    const s = this.latest;
    const g = this.geometry;
    if (s) {
      this.pose(s.robot.q_rad);
      const r = g.ball_radius_m;
      const est = s.pendulum.ball_m.map(num);
      const tru = s.pendulum.truth_ball_m.map(num);
      const icp = s.path.intercept_m.map(num);
      const ref = [tru, est, icp].find((v) => v.every(Number.isFinite));
      const pivot = ref ? new THREE.Vector3(ref[0], 0, g.intercept_height_m + g.length_m) : null;
      const show = (m: THREE.Mesh, v: number[]) => {
        m.visible = v.every(Number.isFinite);
        if (m.visible) {
          m.position.set(v[0], v[1], v[2]);
          m.scale.setScalar(r);
        }
      };
      show(this.ball, est.every(Number.isFinite) ? est : tru);
      show(this.truth, tru);
      if (pivot && this.ball.visible) stretch(this.string, pivot, this.ball.position);
      else this.string.visible = false;
      const target = icp.every(Number.isFinite) ? icp : ref ? [ref[0], 0, g.intercept_height_m] : null;
      this.intercept.visible = target !== null;
      if (target) this.intercept.position.set(target[0], target[1], target[2]);
      // Predicted ball path from the horizon (lateral x on the swing plane).
      const pos = this.predicted.geometry.getAttribute("position") as THREE.BufferAttribute;
      const h = s.pendulum.horizon;
      const n = pivot ? Math.min(h.length, 64) : 0;
      for (let i = 0; i < n && pivot; i++) {
        const x = Math.max(-g.length_m, Math.min(g.length_m, h[i].x_m));
        pos.setXYZ(i, pivot.x, x, pivot.z - Math.sqrt(g.length_m * g.length_m - x * x));
      }
      pos.needsUpdate = true;
      this.predicted.geometry.setDrawRange(0, n);
      this.predicted.computeLineDistances();
      // Planned tool path: home -> intercept point.
      const tp = this.toolPath.geometry.getAttribute("position") as THREE.BufferAttribute;
      if (target) {
        tp.setXYZ(0, g.home_m[0], g.home_m[1], g.home_m[2]);
        tp.setXYZ(1, target[0], target[1], target[2]);
        tp.needsUpdate = true;
        this.toolPath.visible = true;
      } else this.toolPath.visible = false;
    }
    this.renderer.render(this.scene, this.camera);
    this.frames += 1;
    if (s) remember(this.shown, s);
  }
}

/** What the twin last drew, to tell whether a new state would look different. */
type Shown = Float64Array;
const SHOWN_LEN = 7 + 9 + 4;

function visible(s: StateMessage, out: Float64Array): void {
  let k = 0;
  for (let i = 0; i < 7; i++) out[k++] = s.robot.q_rad[i];
  for (const v of [s.pendulum.ball_m, s.pendulum.truth_ball_m, s.path.intercept_m]) for (let i = 0; i < 3; i++) out[k++] = num(v[i]);
  const h = s.pendulum.horizon;
  out[k++] = h.length;
  out[k++] = h.length > 0 ? h[h.length - 1].x_m : 0;
  out[k++] = h.length > 0 ? h[0].x_m : 0;
  out[k++] = h.length > 0 ? h[h.length >> 1].x_m : 0;
}

const scratch = new Float64Array(SHOWN_LEN);

/** True when `s` differs visibly from what was drawn (0.1 mrad, 0.1 mm; NaN flips count). */
function changed(shown: Shown, s: StateMessage): boolean {
  visible(s, scratch);
  for (let i = 0; i < SHOWN_LEN; i++) {
    const a = shown[i], b = scratch[i];
    if (Number.isNaN(a) !== Number.isNaN(b) || Math.abs(a - b) > 1e-4) return true;
  }
  return false;
}

function remember(shown: Shown, s: StateMessage): void {
  visible(s, shown);
}

/** True when WebGL is drawn by the CPU (Chromium's SwiftShader, Mesa's llvmpipe). */
function softwareWebGl(): boolean {
  const gl = document.createElement("canvas").getContext("webgl");
  if (!gl) return false;
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
  gl.getExtension("WEBGL_lose_context")?.loseContext();
  return /swiftshader|llvmpipe|software/i.test(name);
}
