// The 3D view (orbitable, three.js + OrbitControls; a click without a drag picks a spot on the
// model, a drag with Shift held draws a box) and the thumbnail renderer of the gallery.
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { getArrayBuffer, partPath } from "./api.js";

const PALETTE = [0x4e79a7, 0xf28e2b, 0x59a14f, 0xe15759, 0x76b7b2, 0xedc948, 0xb07aa1, 0xff9da7, 0x9c755f,
  0xbab0ac];

export function colourOf(index) {
  return PALETTE[index % PALETTE.length];
}

function lights(scene) {
  scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6);
  sun.position.set(2, 3, 2.5);
  scene.add(sun);
}

// Part geometry is fetched once per part id (GLB from /parts/{id}/mesh) and shared.
const geometryCache = new Map();

export function partGeometry(partId) {
  if (!geometryCache.has(partId)) {
    const promise = getArrayBuffer(partPath(partId) + "/mesh?format=glb").then(async (buffer) => {
      const gltf = await new GLTFLoader().parseAsync(buffer, "");
      let geometry = null;
      gltf.scene.traverse((child) => {
        if (child.isMesh && !geometry) geometry = child.geometry;
      });
      if (!geometry) throw new Error(`part ${partId}: its mesh has no triangles`);
      geometry.computeVertexNormals();
      return geometry;
    });
    promise.catch(() => geometryCache.delete(partId));
    geometryCache.set(partId, promise);
  }
  return geometryCache.get(partId);
}

export class Viewer {
  constructor(container) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(0xf4f5f7);
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    lights(this.scene);
    const grid = new THREE.GridHelper(2.4, 12, 0xc8ccd2, 0xdde0e4);
    grid.position.y = -1;
    this.scene.add(grid);
    this.group = new THREE.Group();
    this.scene.add(this.group);
    this.marker = null;    // the picked spot: a translucent ball
    this.ghost = null;     // a suggestion previewed where the service placed it
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.camera.position.set(2.2, 1.4, 2.6);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.target.set(0, 0, 0);
    this.controls.enableDamping = true;
    this.controls.addEventListener("change", () => this.render());
    new ResizeObserver(() => this.resize()).observe(container);
    this.onPick = null;
    this.onBox = null;
    this.listenForClicks();
    this.listenForBoxes();
    this.resize();
    const tick = () => {
      if (this.controls.update()) this.render();
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  resize() {
    const w = Math.max(1, this.container.clientWidth), h = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }

  // A press and release within a few pixels is a click (a drag orbits): onPick(point) with the
  // model's surface point under the cursor, or onPick(null) when the click missed the model.
  listenForClicks() {
    const canvas = this.renderer.domElement;
    let down = null;
    canvas.addEventListener("pointerdown", (e) => { down = e.button === 0 ? [e.clientX, e.clientY] : null; });
    canvas.addEventListener("pointerup", (e) => {
      if (!down || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4 || !this.onPick) return;
      down = null;
      this.onPick(this.pick(e.clientX, e.clientY));
    });
  }

  // Shift + drag: a rectangle on the screen, turned into a box in the scene (boxFromRect) for
  // onBox(box). The capture listener on the container runs before OrbitControls' own, so the
  // controls are off for that drag and do not pan.
  listenForBoxes() {
    const overlay = document.createElement("div");
    overlay.className = "drag-box";
    overlay.hidden = true;
    this.container.append(overlay);
    let start = null;
    const local = (e) => {
      const r = this.container.getBoundingClientRect();
      return [e.clientX - r.left, e.clientY - r.top];
    };
    this.container.addEventListener("pointerdown", (e) => {
      if (!e.shiftKey || e.button !== 0 || !this.onBox) return;
      this.controls.enabled = false;
      start = [e.clientX, e.clientY];
      e.preventDefault();
    }, true);
    window.addEventListener("pointermove", (e) => {
      if (!start) return;
      const r = this.container.getBoundingClientRect();
      const [x0, y0] = [start[0] - r.left, start[1] - r.top];
      const [x1, y1] = local(e);
      Object.assign(overlay.style, { left: `${Math.min(x0, x1)}px`, top: `${Math.min(y0, y1)}px`,
        width: `${Math.abs(x1 - x0)}px`, height: `${Math.abs(y1 - y0)}px` });
      overlay.hidden = false;
    });
    window.addEventListener("pointerup", (e) => {
      if (!start) return;
      const from = start;
      start = null;
      overlay.hidden = true;
      this.controls.enabled = true;
      if (Math.abs(e.clientX - from[0]) < 4 || Math.abs(e.clientY - from[1]) < 4) return;
      this.onBox(this.boxFromRect(from[0], from[1], e.clientX, e.clientY));
    });
  }

  // A screen rectangle as an axis-aligned box in the scene: the rectangle's corners on the plane
  // facing the camera through the model point under its centre (or the model's centre when it
  // covers none), as deep along the view as the rectangle is wide: {min, max}.
  boxFromRect(x0, y0, x1, y1) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = (x, y) => new THREE.Vector2(((x - rect.left) / rect.width) * 2 - 1,
      -((y - rect.top) / rect.height) * 2 + 1);
    const ray = new THREE.Raycaster();
    const view = new THREE.Vector3();
    this.camera.getWorldDirection(view);
    const hit = this.pick((x0 + x1) / 2, (y0 + y1) / 2);
    const through = hit ? new THREE.Vector3().fromArray(hit)
      : new THREE.Box3().setFromObject(this.group).getCenter(new THREE.Vector3());
    const plane = new THREE.Plane().setFromNormalAndCoplanarPoint(view, through);
    const corners = [[x0, y0], [x1, y0], [x0, y1], [x1, y1]].map(([x, y]) => {
      ray.setFromCamera(ndc(x, y), this.camera);
      return ray.ray.intersectPlane(plane, new THREE.Vector3()) ?? through.clone();
    });
    const depth = Math.max(corners[0].distanceTo(corners[1]), corners[0].distanceTo(corners[2]));
    const points = corners.flatMap((c) => [c.clone().addScaledVector(view, -depth / 2),
      c.clone().addScaledVector(view, depth / 2)]);
    const box = new THREE.Box3().setFromPoints(points);
    return { min: box.min.toArray(), max: box.max.toArray() };
  }

  // The nearest surface point of the assembly under a window position, or null.
  pick(clientX, clientY) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1,
      -((clientY - rect.top) / rect.height) * 2 + 1);
    const ray = new THREE.Raycaster();
    ray.setFromCamera(ndc, this.camera);
    const hit = ray.intersectObjects(this.group.children, false)[0];
    return hit ? hit.point.toArray() : null;
  }

  // The spot the suggestions are for: {point, radius} drawn as a ball, {min, max} as a box
  // (null: none).
  setSpot(spot) {
    if (this.marker) {
      this.scene.remove(this.marker);
      this.marker.geometry.dispose();
      this.marker = null;
    }
    if (spot) {
      const material = new THREE.MeshBasicMaterial({ color: 0xa371f7, transparent: true, opacity: 0.35,
        depthWrite: false });
      if (spot.point) {
        this.marker = new THREE.Mesh(new THREE.SphereGeometry(spot.radius, 24, 16), material);
        this.marker.position.fromArray(spot.point);
      } else {
        const size = spot.max.map((v, i) => v - spot.min[i]);
        this.marker = new THREE.Mesh(new THREE.BoxGeometry(...size), material);
        this.marker.position.fromArray(spot.max.map((v, i) => (v + spot.min[i]) / 2));
      }
      this.scene.add(this.marker);
    }
    this.render();
  }

  // A suggestion shown, translucent, where the service placed it (null: none).
  async setGhost(item) {
    const token = (this.ghostToken = (this.ghostToken ?? 0) + 1);
    const geometry = item ? await partGeometry(item.partId) : null;
    if (token !== this.ghostToken) return;
    if (this.ghost) this.scene.remove(this.ghost);
    this.ghost = null;
    if (geometry) {
      this.ghost = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({
        color: item.colour, transparent: true, opacity: 0.55, depthWrite: false }));
      this.ghost.position.fromArray(item.translation);
      this.ghost.scale.fromArray(item.scale ?? [1, 1, 1]);
      this.scene.add(this.ghost);
    }
    this.render();
  }

  // items: [{partId, translation, scale?, colour}] and an optional cloud geometry (uploaded start).
  async show(items, cloudGeometry) {
    const meshes = await Promise.all(items.map(async (item) => {
      const geometry = await partGeometry(item.partId);
      const mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({
        color: item.colour, roughness: 0.65, metalness: 0.05 }));
      mesh.position.fromArray(item.translation);
      mesh.scale.fromArray(item.scale ?? [1, 1, 1]);
      mesh.userData.partId = item.partId;
      return mesh;
    }));
    this.group.clear();
    if (cloudGeometry) {
      this.group.add(new THREE.Mesh(cloudGeometry, new THREE.MeshStandardMaterial({
        color: 0x9aa3ad, roughness: 0.8, side: THREE.DoubleSide })));
    }
    meshes.forEach((m) => this.group.add(m));
    this.render();
  }
}

// One offscreen renderer draws every thumbnail (browsers allow only a few WebGL contexts).
export class Thumbnailer {
  constructor(size) {
    this.size = size;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setSize(size, size, false);
    this.renderer.setClearColor(0xffffff);
    this.scene = new THREE.Scene();
    lights(this.scene);
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
  }

  // A data URL of the part's mesh, coloured, seen from the front-right, framed to fit.
  async draw(partId, colour) {
    const geometry = await partGeometry(partId);
    const mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({ color: colour, roughness: 0.6 }));
    this.scene.add(mesh);
    geometry.computeBoundingSphere();
    const r = geometry.boundingSphere.radius || 1;
    const c = geometry.boundingSphere.center;
    const dir = new THREE.Vector3(1.1, 0.8, 1.4).normalize();
    this.camera.position.copy(c).addScaledVector(dir, r * 3.2);
    this.camera.lookAt(c);
    this.renderer.render(this.scene, this.camera);
    const url = this.renderer.domElement.toDataURL("image/png");
    this.scene.remove(mesh);
    mesh.material.dispose();
    return url;
  }
}
