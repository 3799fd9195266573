// The modeling page: pick a start, see the assembly, add suggestions, auto-complete, download.
//
// State: the placed catalog parts (id, translation in the canonical frame) and, when the start
// is an uploaded mesh, that mesh normalised to the canonical frame with its surface samples.
// Every edit pushes the previous state on the undo stack. Suggestions, auto-completion and
// alternatives come from the service (/suggest, /assemble); the download from /export.
import { base64ToFloats, floatsToBase64, getJson, partPath, postForBlob, postJson } from "./api.js";
import { areaWeighted, normalise, parseMeshFile, sampleSurface } from "./geometry.js";
import { Thumbnailer, Viewer, colourOf } from "./view.js";

const QUERY_POINTS = 2048;       // points sent per query (the service resamples to its N)
const GALLERY_SIZE = 12;         // suggestions shown
const AUTO_PARTS = 6;            // parts auto-complete may add
const TREE_DEPTH = 3;            // depth of the alternatives tree
const UPLOAD_RADIUS = 0.6;       // an uploaded partial mesh is scaled to this radius

const $ = (id) => document.getElementById(id);

const state = { category: null, parts: [], cloud: null };
const undoStack = [];
const redoStack = [];
let viewer;
let thumbnails;
let busyCount = 0;
let refreshToken = 0;

// ------------------------------------------------------------------ status and busy flag

function setStatus(text, isError = false) {
  const el = $("status");
  el.textContent = text;
  el.classList.toggle("error", isError);
}

async function busy(label, fn) {
  busyCount++;
  $("status").dataset.busy = "true";
  setStatus(label + "…");
  try {
    return await fn();
  } catch (err) {
    setStatus(err.message || String(err), true);
    return undefined;
  } finally {
    busyCount--;
    if (busyCount === 0) {
      $("status").dataset.busy = "false";
      if (!$("status").classList.contains("error")) setStatus(describe());
    }
  }
}

function describe() {
  const n = state.parts.length + (state.cloud ? 1 : 0);
  return n ? `${state.parts.length} part${state.parts.length === 1 ? "" : "s"}` +
    (state.cloud ? " on the uploaded mesh" : "") : "Pick a category and a start part, or upload a mesh.";
}

// ------------------------------------------------------------------ part data (cached)

const records = new Map();
const samples = new Map();

function partRecord(partId) {
  if (!records.has(partId)) records.set(partId, getJson(partPath(partId)));
  return records.get(partId);
}

function partSamples(partId) {
  if (!samples.has(partId)) {
    samples.set(partId, getJson(partPath(partId) + "/points?encoding=base64")
      .then((body) => base64ToFloats(body.points_base64)));
  }
  return samples.get(partId);
}

// The current assembly as query points (area-weighted over parts and the uploaded mesh).
async function queryPoints() {
  const pieces = await Promise.all(state.parts.map(async (p) => {
    const [pts, rec] = await Promise.all([partSamples(p.partId), partRecord(p.partId)]);
    const placed = new Float32Array(pts.length);
    for (let i = 0; i < pts.length; i += 3) {
      placed[i] = pts[i] + p.translation[0];
      placed[i + 1] = pts[i + 1] + p.translation[1];
      placed[i + 2] = pts[i + 2] + p.translation[2];
    }
    return { points: placed, area: rec.area };
  }));
  if (state.cloud) pieces.push({ points: state.cloud.points, area: state.cloud.area });
  return areaWeighted(pieces, QUERY_POINTS, 7);
}

// ------------------------------------------------------------------ edits and history

function snapshot() {
  return { category: state.category, parts: state.parts.map((p) => ({ ...p })), cloud: state.cloud };
}

function restore(snap) {
  state.category = snap.category;
  state.parts = snap.parts.map((p) => ({ ...p }));
  state.cloud = snap.cloud;
}

function edit(mutate) {
  undoStack.push(snapshot());
  redoStack.length = 0;
  mutate();
  return refresh();
}

function undo() {
  if (!undoStack.length) return undefined;
  redoStack.push(snapshot());
  restore(undoStack.pop());
  return refresh();
}

function redo() {
  if (!redoStack.length) return undefined;
  undoStack.push(snapshot());
  restore(redoStack.pop());
  return refresh();
}

function placedPart(entry) {
  return { partId: entry.part_id, translation: entry.translation, label: entry.label ?? null };
}

// ------------------------------------------------------------------ rendering

function renderPartList() {
  const list = $("part-list");
  list.replaceChildren();
  state.parts.forEach((p, i) => {
    const li = document.createElement("li");
    li.dataset.testid = "placed-part";
    li.dataset.partId = p.partId;
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = "#" + colourOf(i).toString(16).padStart(6, "0");
    li.append(swatch, `${p.partId}${p.label ? " (" + p.label + ")" : ""}`);
    list.append(li);
  });
  $("undo-button").disabled = !undoStack.length;
  $("redo-button").disabled = !redoStack.length;
  const empty = !state.parts.length && !state.cloud;
  for (const id of ["autocomplete-button", "alternatives-button"]) $(id).disabled = empty;
  $("download-button").disabled = !state.parts.length;
}

async function renderGallery(answer, token) {
  const gallery = $("gallery");
  const weights = new Map(answer.modes.map((m) => [m.mode, m.weight]));
  const groups = new Map();
  for (const s of answer.suggestions) {
    if (!groups.has(s.mode)) groups.set(s.mode, []);
    groups.get(s.mode).push(s);
  }
  const order = [...groups.keys()].sort((a, b) => weights.get(b) - weights.get(a) || a - b);
  const sections = [];
  const cards = [];
  for (const mode of order) {
    const section = document.createElement("section");
    section.className = "mode-group";
    section.dataset.testid = "mode-group";
    section.dataset.mode = String(mode);
    const h = document.createElement("h3");
    h.textContent = `Mode ${mode} · weight ${weights.get(mode).toFixed(2)}`;
    const row = document.createElement("div");
    row.className = "cards";
    for (const s of groups.get(mode)) {
      const card = document.createElement("button");
      card.className = "suggestion";
      card.dataset.testid = "suggestion-card";
      card.dataset.partId = s.part_id;
      card.dataset.mode = String(mode);
      card.title = `${s.part_id}: score ${s.score.toFixed(1)}, contact offset ` +
        s.contact_offset.map((v) => v.toFixed(3)).join(", ");
      const img = document.createElement("img");
      img.alt = s.part_id;
      img.width = img.height = 96;
      const caption = document.createElement("span");
      caption.textContent = s.label ? `${s.label} · ${s.shape_id}` : s.part_id;
      card.append(img, caption);
      card.addEventListener("click", () => busy("Adding " + s.part_id, () => edit(() => {
        state.parts.push(placedPart(s));
        if (!state.category) state.category = s.category;
      })));
      row.append(card);
      cards.push({ img, s, mode });
    }
    section.append(h, row);
    sections.push(section);
  }
  if (token !== refreshToken) return;
  gallery.replaceChildren(...sections);
  if (!answer.suggestions.length) gallery.textContent = "No suggestions.";
  for (const { img, s, mode } of cards) {
    if (token !== refreshToken) return;
    img.src = await thumbnails.draw(s.part_id, colourOf(mode + 3));
  }
}

async function refresh() {
  const token = ++refreshToken;
  renderPartList();
  $("alternatives-tree").replaceChildren();
  const items = state.parts.map((p, i) => ({ ...p, colour: colourOf(i) }));
  await viewer.show(items, state.cloud ? state.cloud.geometry : null);
  if (!state.parts.length && !state.cloud) {
    $("gallery").replaceChildren();
    return;
  }
  const points = await queryPoints();
  const answer = await postJson("/suggest", {
    points_base64: floatsToBase64(points), k: GALLERY_SIZE, diversity: $("diversity-toggle").checked,
    refine_contact: $("refine-toggle").checked, ...(state.category ? { category: state.category } : {}),
  });
  if (token === refreshToken) await renderGallery(answer, token);
}

// ------------------------------------------------------------------ assembly requests

async function assembleBody(extra) {
  const body = {
    max_parts: AUTO_PARTS, refine_contact: $("refine-toggle").checked,
    ...(state.category ? { category: state.category } : {}), ...extra,
  };
  if (state.parts.length) {
    body.parts = state.parts.map((p) => ({ part_id: p.partId, translation: p.translation }));
  }
  if (state.cloud) body.points_base64 = floatsToBase64(state.cloud.points);
  return body;
}

async function autoComplete() {
  const answer = await postJson("/assemble", await assembleBody({}));
  if (!answer.steps.length) {
    setStatus(`Nothing to add (${answer.stop_reason}).`);
    return;
  }
  await edit(() => {
    for (const step of answer.steps) state.parts.push(placedPart(step));
    if (!state.category) state.category = answer.category;
  });
}

async function showAlternatives() {
  const answer = await postJson("/assemble", await assembleBody({ branching: 2, max_parts: TREE_DEPTH }));
  const tree = $("alternatives-tree");
  const children = new Map();
  for (const n of answer.nodes) {
    const key = n.parent ?? "root";
    if (!children.has(key)) children.set(key, []);
    children.get(key).push(n);
  }
  const byId = new Map(answer.nodes.map((n) => [n.node, n]));
  const build = (key) => {
    const ul = document.createElement("ul");
    for (const n of children.get(key) ?? []) {
      const li = document.createElement("li");
      const button = document.createElement("button");
      button.className = "tree-node";
      button.dataset.testid = "tree-node";
      button.dataset.node = String(n.node);
      button.textContent = `${n.label ?? "part"} · ${n.part_id}`;
      button.title = "Use this branch (every part from the current assembly down to here)";
      button.addEventListener("click", () => busy("Applying branch", () => edit(() => {
        const path = [];
        for (let m = n; m; m = m.parent === null ? null : byId.get(m.parent)) path.unshift(m);
        for (const step of path) state.parts.push(placedPart(step));
        if (!state.category) state.category = answer.category;
      })));
      li.append(button);
      if (children.has(n.node)) li.append(build(n.node));
      ul.append(li);
    }
    return ul;
  };
  tree.replaceChildren(answer.nodes.length ? build("root") : `No alternatives (${answer.stop_reason}).`);
}

async function download() {
  const format = $("export-format").value;
  const blob = await postForBlob("/export", {
    format, parts: state.parts.map((p) => ({ part_id: p.partId, translation: p.translation })),
  });
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = `assembly.${format}`;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ------------------------------------------------------------------ start

async function loadCategories() {
  const cats = await getJson("/categories");
  const select = $("category-select");
  select.replaceChildren(...cats.map((c) => new Option(`${c.name} (${c.parts})`, c.name)));
  await loadStartParts();
}

async function loadStartParts() {
  const category = $("category-select").value;
  const page = await getJson(`/parts?category=${encodeURIComponent(category)}&limit=100`);
  $("start-part-select").replaceChildren(...page.items.map((p) =>
    new Option(`${p.part_id}${p.label ? " · " + p.label : ""}`, p.part_id)));
}

async function startFromPart() {
  const partId = $("start-part-select").value;
  if (!partId) return;
  const rec = await partRecord(partId);
  await edit(() => {
    state.category = rec.category;
    state.cloud = null;
    state.parts = [{ partId, translation: rec.translation, label: rec.label }];
  });
}

async function startFromMesh(file) {
  const geometry = normalise(await parseMeshFile(file), UPLOAD_RADIUS);
  const { points, area } = sampleSurface(geometry, QUERY_POINTS, 1);
  await edit(() => {
    state.category = null;
    state.parts = [];
    state.cloud = { geometry, points, area, name: file.name };
  });
}

function main() {
  viewer = new Viewer($("viewport"));
  thumbnails = new Thumbnailer(96);
  $("category-select").addEventListener("change", () => busy("Loading parts", loadStartParts));
  $("start-button").addEventListener("click", () => busy("Starting", startFromPart));
  $("mesh-upload").addEventListener("change", (e) => {
    const file = e.target.files?.[0];
    if (file) busy("Reading " + file.name, () => startFromMesh(file));
  });
  $("undo-button").addEventListener("click", () => busy("Undoing", undo));
  $("redo-button").addEventListener("click", () => busy("Redoing", redo));
  $("autocomplete-button").addEventListener("click", () => busy("Auto-completing", autoComplete));
  $("alternatives-button").addEventListener("click", () => busy("Growing alternatives", showAlternatives));
  $("download-button").addEventListener("click", () => busy("Exporting", download));
  for (const id of ["diversity-toggle", "refine-toggle"]) {
    $(id).addEventListener("change", () => busy("Updating suggestions", refresh));
  }
  renderPartList();
  busy("Loading categories", loadCategories);
}

main();
