// Geometry helpers of the page: uploaded meshes to one normalised geometry, surface sampling,
// and the area-weighted query the service expects.
import * as THREE from "three";
import { mergeGeometries } from "three/examples/jsm/utils/BufferGeometryUtils.js";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { OBJLoader } from "three/examples/jsm/loaders/OBJLoader.js";
import { PLYLoader } from "three/examples/jsm/loaders/PLYLoader.js";
import { STLLoader } from "three/examples/jsm/loaders/STLLoader.js";

// A small seeded generator (mulberry32): the same upload gives the same samples.
export function rng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

function geometriesOf(object) {
  const out = [];
  object.updateMatrixWorld(true);
  object.traverse((child) => {
    if (child.isMesh && child.geometry) {
      let g = child.geometry.clone();
      g.applyMatrix4(child.matrixWorld);
      g = g.index ? g.toNonIndexed() : g;
      for (const name of Object.keys(g.attributes)) if (name !== "position") g.deleteAttribute(name);
      out.push(g);
    }
  });
  return out;
}

// Parse an uploaded mesh file (OBJ, STL, PLY, GLB/glTF) into one non-indexed geometry.
export async function parseMeshFile(file) {
  const name = file.name.toLowerCase();
  const ext = name.slice(name.lastIndexOf(".") + 1);
  const buffer = await file.arrayBuffer();
  let geometries;
  if (ext === "obj") {
    geometries = geometriesOf(new OBJLoader().parse(new TextDecoder().decode(buffer)));
  } else if (ext === "stl") {
    geometries = [new STLLoader().parse(buffer)];
  } else if (ext === "ply") {
    geometries = [new PLYLoader().parse(buffer)];
  } else if (ext === "glb" || ext === "gltf") {
    const gltf = await new GLTFLoader().parseAsync(buffer, "");
    geometries = geometriesOf(gltf.scene);
  } else {
    throw new Error(`unsupported mesh format .${ext}: use OBJ, STL, PLY, GLB or glTF`);
  }
  geometries = geometries.map((g) => {
    let h = g.index ? g.toNonIndexed() : g;
    for (const name of Object.keys(h.attributes)) if (name !== "position") h.deleteAttribute(name);
    return h;
  });
  if (!geometries.length) throw new Error(`${file.name}: no triangles found`);
  return mergeGeometries(geometries, false);
}

// Centre a geometry at its bounding-box centre and scale it to the given bounding-sphere radius.
export function normalise(geometry, radius) {
  geometry.computeBoundingBox();
  const centre = new THREE.Vector3();
  geometry.boundingBox.getCenter(centre);
  geometry.translate(-centre.x, -centre.y, -centre.z);
  geometry.computeBoundingSphere();
  const r = geometry.boundingSphere.radius || 1;
  geometry.scale(radius / r, radius / r, radius / r);
  geometry.computeVertexNormals();
  return geometry;
}

// Bring a geometry from an answer's frame into the canonical one: the inverse of the frame
// (x = scale * rotation @ v + center), v = rotation^T (x - center) / scale.
export function toCanonical(geometry, frame) {
  const [c, r, s] = [frame.center, frame.rotation, frame.scale];
  const m = new THREE.Matrix4().set(
    r[0][0] / s, r[1][0] / s, r[2][0] / s, 0,
    r[0][1] / s, r[1][1] / s, r[2][1] / s, 0,
    r[0][2] / s, r[1][2] / s, r[2][2] / s, 0,
    0, 0, 0, 1);
  geometry.translate(-c[0], -c[1], -c[2]);
  geometry.applyMatrix4(m);
  geometry.computeVertexNormals();
}

// Area-weighted surface samples of a non-indexed geometry: {points: Float32Array(3n), area}.
export function sampleSurface(geometry, n, seed) {
  const pos = geometry.attributes.position.array;
  const triangles = pos.length / 9;
  const cumulative = new Float64Array(triangles);
  const a = new THREE.Vector3(), b = new THREE.Vector3(), c = new THREE.Vector3();
  let total = 0;
  for (let t = 0; t < triangles; t++) {
    a.fromArray(pos, 9 * t); b.fromArray(pos, 9 * t + 3); c.fromArray(pos, 9 * t + 6);
    total += b.sub(a).cross(c.sub(a)).length() / 2;
    cumulative[t] = total;
  }
  if (!(total > 0)) throw new Error("the mesh has no surface area");
  const random = rng(seed);
  const out = new Float32Array(3 * n);
  for (let i = 0; i < n; i++) {
    const target = random() * total;
    let lo = 0, hi = triangles - 1;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (cumulative[mid] < target) lo = mid + 1; else hi = mid;
    }
    let r1 = Math.sqrt(random()), r2 = random();
    for (let k = 0; k < 3; k++) {
      const p0 = pos[9 * lo + k], p1 = pos[9 * lo + 3 + k], p2 = pos[9 * lo + 6 + k];
      out[3 * i + k] = (1 - r1) * p0 + r1 * (1 - r2) * p1 + r1 * r2 * p2;
    }
  }
  return { points: out, area: total };
}

// The query: `n` points over the pieces, each piece's share proportional to its area.
// pieces: [{points: Float32Array(3m) already placed, area}]
export function areaWeighted(pieces, n, seed) {
  const areas = pieces.map((p) => Math.max(p.area, 1e-9));
  const sum = areas.reduce((x, y) => x + y, 0);
  const random = rng(seed);
  const out = new Float32Array(3 * n);
  let written = 0;
  pieces.forEach((piece, j) => {
    const m = piece.points.length / 3;
    const count = j === pieces.length - 1 ? n - written : Math.max(1, Math.floor((n * areas[j]) / sum));
    for (let i = 0; i < count && written < n; i++, written++) {
      const pick = Math.floor(random() * m);
      out.set(piece.points.subarray(3 * pick, 3 * pick + 3), 3 * written);
    }
  });
  return out.subarray(0, 3 * written);
}
