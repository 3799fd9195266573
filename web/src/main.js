// The modeling page: pick a start, see the assembly, add suggestions, ask for parts at a spot,
// auto-complete, download.
//
// State: the placed catalog parts (id, translation and fitted scale in the canonical frame), the
// category the suggestions stay in (null: any, the dropdown's "Any category") and, when the start
// is an uploaded mesh, that mesh brought into the canonical frame (the frame the service fitted
// to it) with its surface samples.
// Every edit pushes the previous state on the undo stack. The spot the user clicked is a
// question, not an edit: it is not in the history and any edit clears it. Suggestions,
// auto-completion and alternatives come from the service (/suggest, /assemble); the download
// from /export.
import { ApiError, base64ToFloats, floatsToBase64, getJson, partPath, postForBlob, postJson } from "./api.js";
import { areaWeighted, normalise, parseMeshFile, sampleSurface, toCanonical } from "./geometry.js";
import { Thumbnailer, Viewer, colourOf } from "./view.js";

const QUERY_POINTS = 2048;       // points sent per query (the service resamples to its N)
const GALLERY_SIZE = 12;         // suggestions shown
const AUTO_PARTS = 6;            // parts auto-complete may add
const TREE_DEPTH = 3;            // depth of the alternatives tree
const UPLOAD_RADIUS = 0.6;       // an upload the service cannot fit a frame to is scaled to this radius
const START_PAGE = 50;           // start parts per page of the picker
const PROGRESS_AFTER_MS = 300;   // a step taking longer shows the progress indicator
const SEARCH_DELAY_MS = 250;     // typing pause before the picker searches

const $ = (id) => document.getElementById(id);

const state = { category: null, parts: [], cloud: null };
const undoStack = [];
const redoStack = [];
const picker = { offset: 0, total: 0, query: "", token: 0 };
let spot = null;                 // {point, radius} (a click) or {min, max} (a Shift-drag), canonical; or null
let viewer;
let thumbnails;
let busyCount = 0;
let refreshToken = 0;
let progressTimer = null;

// ------------------------------------------------------------------ status, progress, notices

// One line (the layout gives it a fixed height); the title holds the whole text.
function setStatus(text, isError = false) {
  const el = $("status");
  el.textContent = text;
  el.title = text;
  el.classList.toggle("error", isError);
}

function showProgress(label) {
  const el = $("progress");
  $("progress-label").textContent = label + "…";
  if (el.hidden) el.dataset.shown = String(Number(el.dataset.shown || 0) + 1);  // for tests
  el.hidden = false;
}

// Runs one step of the page: the status says what is going on, a progress indicator appears if
// it takes longer than PROGRESS_AFTER_MS, errors end in the status line.
async function busy(label, fn) {
  busyCount++;
  $("status").dataset.busy = "true";
  setStatus(label + "…");
  clearTimeout(progressTimer);
  progressTimer = setTimeout(() => showProgress(label), PROGRESS_AFTER_MS);
  try {
    return await fn();
  } catch (err) {
    setStatus(err.message || String(err), true);
    notify(err.message || String(err), "error");  // the whole message, where it has room
    return undefined;
  } finally {
    busyCount--;
    if (busyCount === 0) {
      clearTimeout(progressTimer);
      $("progress").hidden = true;
      $("status").dataset.busy = "false";
      if (!$("status").classList.contains("error")) setStatus(describe());
    }
  }
}

function notify(text, kind = "info") {
  $("notice-text").textContent = text;
  $("notice").classList.toggle("warn", kind === "warn");
  $("notice").classList.toggle("error", kind === "error");
  $("notice").dataset.kind = kind;
  $("notice").hidden = false;
}

function clearNotice() {
  $("notice").hidden = true;
}

function describe() {
  const n = state.parts.length + (state.cloud ? 1 : 0);
  return n ? `${state.parts.length} part${state.parts.length === 1 ? "" : "s"}` +
    (state.cloud ? " on the uploaded mesh" + fittedNote(state.cloud.frame) : "") :
    "Pick a category and a start part, or upload a mesh.";
}

// What the fitted frame of an upload was, in the file's units: the designer can check it.
function fittedNote(frame) {
  if (!frame) return " (scaled by its own box: no frame could be fitted)";
  return ` (read ${frame.up_axis} up, the complete object about ${(2 * frame.radius).toPrecision(3)} ` +
    "units across)";
}

function percent(share) {
  const p = 100 * share;
  return p >= 1 ? `${Math.round(p)}%` : p >= 0.1 ? `${p.toFixed(1)}%` : "<0.1%";
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
    const [sx, sy, sz] = p.scale;
    for (let i = 0; i < pts.length; i += 3) {
      placed[i] = sx * pts[i] + p.translation[0];
      placed[i + 1] = sy * pts[i + 1] + p.translation[1];
      placed[i + 2] = sz * pts[i + 2] + p.translation[2];
    }
    // A scaled part's area, roughly (exact for a uniform scale): only the points' shares use it.
    return { points: placed, area: rec.area * (sx * sy + sy * sz + sx * sz) / 3 };
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
  setSpot(null);
  return refresh();
}

function undo() {
  if (!undoStack.length) return undefined;
  redoStack.push(snapshot());
  restore(undoStack.pop());
  setSpot(null);
  return refresh();
}

function redo() {
  if (!redoStack.length) return undefined;
  undoStack.push(snapshot());
  restore(redoStack.pop());
  setSpot(null);
  return refresh();
}

function placedPart(entry) {
  return { partId: entry.part_id, translation: entry.translation, scale: entry.scale ?? [1, 1, 1],
    label: entry.label ?? null };
}

// A catalog part added while no category is chosen decides it (the dropdown shows it).
function adoptCategory(category) {
  if (!state.category && category) state.category = category;
}

// ------------------------------------------------------------------ the spot

function spotName(value) {
  const fmt = (v) => `(${v.map((x) => x.toFixed(2)).join(", ")})`;
  return value.point ? `the spot ${fmt(value.point)}` : `the box ${fmt(value.min)}–${fmt(value.max)}`;
}

function setSpot(value) {
  spot = value;
  viewer.setSpot(spot);
  $("spot-info").hidden = !spot;
  $("spot-hint").hidden = !!spot;
  $("spot-radius").parentElement.hidden = !spot?.point;
  if (spot) $("spot-text").textContent = `Parts for ${spotName(spot)}`;
}

function pickBox(box) {
  if (!state.parts.length && !state.cloud) return;
  clearNotice();
  setSpot(box);
  busy("Finding parts for this box", refreshSuggestions);
}

function pickSpot(point) {
  if (!state.parts.length && !state.cloud) return;
  if (!point) {
    notify("That click missed the model: click on a part where the new part should attach.", "warn");
    return;
  }
  clearNotice();
  setSpot({ point, radius: Number($("spot-radius").value) });
  busy("Finding parts for this spot", refreshSuggestions);
}

// ------------------------------------------------------------------ rendering

function renderPartList() {
  const list = $("part-list");
  list.replaceChildren();
  state.parts.forEach((p, i) => {
    const li = document.createElement("li");
    li.dataset.testid = "placed-part";
    li.dataset.partId = p.partId;
    li.dataset.translation = p.translation.map((v) => v.toFixed(5)).join(",");
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
  const select = $("category-select");
  if (select.value !== (state.category ?? "")) {
    select.value = state.category ?? "";
    picker.offset = 0;
    busy("Loading parts", loadStartParts);
  }
}

// When no category is chosen: what the service read from the shape (model v3 has a head for it).
function renderInferred(answer) {
  const el = $("inferred-category");
  el.hidden = !!state.category;
  if (state.category) return;
  const inferred = answer.inferred_category;
  if (!inferred) {
    el.textContent = "No category chosen: suggestions come from every category (this model does not " +
      "read one from the shape).";
  } else {
    el.textContent = `No category chosen: the model reads this as a ${inferred.category} ` +
      `(${percent(inferred.confidence)} sure)` + (inferred.applied ? ", and keeps the suggestions in it."
        : ", not sure enough: suggestions come from every category.");
  }
  el.dataset.category = inferred ? inferred.category : "";
}

// Mode groups headed by the mode's weight as a share (what share of the model's expectation that
// kind of part is), ordered by it.
function groupsOf(answer) {
  const weights = new Map(answer.modes.map((m) => [m.mode, m.weight]));
  const groups = new Map();
  for (const s of answer.suggestions) {
    if (!groups.has(s.mode)) groups.set(s.mode, []);
    groups.get(s.mode).push(s);
  }
  return [...groups.entries()].map(([mode, items]) => ({ mode, share: weights.get(mode), items }))
    .sort((a, b) => b.share - a.share || a.mode - b.mode);
}

function groupHeading(group) {
  const h = document.createElement("h3");
  const bar = document.createElement("span");
  bar.className = "share";
  const fill = document.createElement("span");
  fill.style.width = `${Math.max(2, Math.round(100 * group.share))}%`;
  bar.append(fill);
  const counts = new Map();
  for (const s of group.items) if (s.label) counts.set(s.label, (counts.get(s.label) ?? 0) + 1);
  const kinds = [...counts.entries()].sort((a, b) => b[1] - a[1]).slice(0, 2).map(([label]) => label);
  const note = document.createElement("span");
  note.className = "group-note";
  note.textContent = kinds.length ? `· ${kinds.join(", ")}` : "";
  const strong = document.createElement("strong");
  strong.textContent = `${percent(group.share)} likely`;
  h.append(bar, strong, note);
  h.title = `The model expects this kind of part with probability ${percent(group.share)} ` +
    `(mode ${group.mode} of its mixture).`;
  return h;
}

function suggestionCard(s, mode) {
  const card = document.createElement("button");
  card.className = "suggestion";
  card.dataset.testid = "suggestion-card";
  card.dataset.partId = s.part_id;
  card.dataset.mode = String(mode);
  card.title = `${s.part_id}: score ${s.score.toFixed(1)}; hover to see where it goes, click to add it`;
  const img = document.createElement("img");
  img.alt = s.part_id;
  img.width = img.height = 96;
  const caption = document.createElement("span");
  caption.textContent = s.label ? `${s.label} · ${s.shape_id}` : s.part_id;
  card.append(img, caption);
  const ghost = { partId: s.part_id, translation: s.translation, scale: s.scale, colour: colourOf(mode + 3) };
  const showError = (err) => setStatus(err.message || String(err), true);
  card.addEventListener("mouseenter", () => viewer.setGhost(ghost).catch(showError));
  card.addEventListener("mouseleave", () => viewer.setGhost(null).catch(showError));
  card.addEventListener("click", () => busy("Adding " + s.part_id, () => edit(() => {
    state.parts.push(placedPart(s));
    adoptCategory(s.category);
  })));
  return { card, img };
}

async function renderGallery(answer, token) {
  const sections = [];
  const cards = [];
  for (const group of groupsOf(answer)) {
    const section = document.createElement("section");
    section.className = "mode-group";
    section.dataset.testid = "mode-group";
    section.dataset.mode = String(group.mode);
    section.dataset.share = String(group.share);
    const row = document.createElement("div");
    row.className = "cards";
    for (const s of group.items) {
      const { card, img } = suggestionCard(s, group.mode);
      row.append(card);
      cards.push({ img, s, mode: group.mode });
    }
    section.append(groupHeading(group), row);
    sections.push(section);
  }
  if (token !== refreshToken) return;
  const gallery = $("gallery");
  gallery.replaceChildren(...sections);
  if (!answer.suggestions.length) {
    const empty = document.createElement("p");
    empty.className = "empty";
    empty.dataset.testid = "gallery-empty";
    const why = answer.warnings.find((w) => w.code === "region_empty");
    empty.textContent = why ? `Nothing fits this spot: ${why.message}.` : "No suggestions.";
    gallery.append(empty);
  }
  for (const { img, s, mode } of cards) {
    if (token !== refreshToken) return;
    img.src = await thumbnails.draw(s.part_id, colourOf(mode + 3));
  }
}

async function refreshSuggestions() {
  const token = ++refreshToken;
  viewer.setGhost(null);
  if (!state.parts.length && !state.cloud) {
    $("gallery").replaceChildren();
    $("inferred-category").hidden = true;
    return;
  }
  const points = await queryPoints();
  const answer = await postJson("/suggest", {
    points_base64: floatsToBase64(points), k: GALLERY_SIZE, diversity: $("diversity-toggle").checked,
    refine_contact: $("refine-toggle").checked, ...(state.category ? { category: state.category } : {}),
    ...(spot ? { region: spot } : {}),
  });
  if (token !== refreshToken) return;
  renderInferred(answer);
  // What the service cannot vouch for (a shape of no kind it knows, a frame far off) is said, not hidden.
  const doubt = answer.warnings.find((w) => w.guess);
  if (doubt) notify(`These suggestions are guesses: ${doubt.message}.`, "warn");
  if (spot && answer.region) {
    $("spot-text").textContent = `Parts for ${spotName(spot)}: ` +
      `${answer.region.inside} of the ${answer.region.placed} best candidates are placed there`;
  }
  await renderGallery(answer, token);
}

async function refresh() {
  renderPartList();
  clearTree();
  const items = state.parts.map((p, i) => ({ ...p, colour: colourOf(i) }));
  await viewer.show(items, state.cloud ? state.cloud.geometry : null);
  await refreshSuggestions();
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

// Why an assembly stopped: the service's own words (service.modeling.assembly.STOP_REASONS,
// sent as stop_message), so the page has no second copy to fall behind.
function stopReason(answer) {
  return `${answer.stop_message ?? "it stopped"} (${answer.stop_reason})`;
}

async function autoComplete() {
  clearNotice();
  const answer = await postJson("/assemble", await assembleBody({}));
  if (!answer.steps.length) {
    notify(`Auto-complete added nothing: ${stopReason(answer)}. Add a suggestion by hand, ` +
      "or click the model where a part should go.", "warn");
    return;
  }
  await edit(() => {
    for (const step of answer.steps) state.parts.push(placedPart(step));
    adoptCategory(answer.category);
  });
  const n = answer.steps.length;
  notify(`Auto-complete added ${n} part${n === 1 ? "" : "s"}${addedBy(answer.steps)}; ` +
    `it stopped because ${stopReason(answer)}.`);
}

// Which parts a rule other than "the most likely" added, in the service's own words
// (service.modeling.assembly.ADD_REASONS, sent as added_message): ", 1 of them because ...".
function addedBy(steps) {
  const counts = new Map();
  for (const s of steps) {
    if (s.added_by && s.added_by !== "likely") counts.set(s.added_message, (counts.get(s.added_message) ?? 0) + 1);
  }
  return [...counts].map(([why, k]) => `, ${k} of them because ${why}`).join("");
}

function clearTree() {
  const hint = document.createElement("p");
  hint.className = "hint";
  hint.textContent = "\u201cShow alternatives\u201d grows a tree of completions here; a click applies a branch.";
  $("alternatives-tree").replaceChildren(hint);
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
        adoptCategory(answer.category);
      })));
      li.append(button);
      if (children.has(n.node)) li.append(build(n.node));
      ul.append(li);
    }
    return ul;
  };
  tree.replaceChildren(answer.nodes.length ? build("root")
    : `No alternatives: ${stopReason(answer)}.`);
}

async function download() {
  const format = $("export-format").value;
  const blob = await postForBlob("/export", {
    format, parts: state.parts.map((p) => ({ part_id: p.partId, translation: p.translation, scale: p.scale })),
  });
  const name = `assembly.${format}`;
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
  const n = state.parts.length;
  notify(`Downloaded ${name}: ${n} part${n === 1 ? "" : "s"}, ${Math.max(1, Math.round(blob.size / 1024))} KB` +
    (state.cloud ? " (the uploaded mesh is not in it: it stays yours)." : "."));
}

// ------------------------------------------------------------------ start

async function loadCategories() {
  const cats = await getJson("/categories");
  const select = $("category-select");
  select.replaceChildren(new Option("Any category", ""),
    ...cats.map((c) => new Option(`${c.name} (${c.parts})`, c.name)));
  select.selectedIndex = cats.length ? 1 : 0;
  state.category = select.value || null;
  await loadStartParts();
}

// One page of the start-part picker: the chosen category, the search text, the page's offset.
async function loadStartParts() {
  const token = ++picker.token;
  const params = new URLSearchParams({ offset: String(picker.offset), limit: String(START_PAGE) });
  const category = $("category-select").value;
  if (category) params.set("category", category);
  if (picker.query) params.set("q", picker.query);
  const page = await getJson(`/parts?${params}`);
  if (token !== picker.token) return;
  picker.total = page.total;
  const select = $("start-part-select");
  select.replaceChildren(...page.items.map((p) =>
    new Option(`${p.part_id}${p.label ? " · " + p.label : ""}`, p.part_id)));
  if (page.items.length) select.selectedIndex = 0;
  $("start-page-info").textContent = page.total
    ? `${picker.offset + 1}–${picker.offset + page.items.length} of ${page.total}` : "no part matches";
  $("start-prev").disabled = picker.offset === 0;
  $("start-next").disabled = picker.offset + page.items.length >= page.total;
  $("start-button").disabled = !page.items.length;
  await previewStart();
}

async function previewStart() {
  const partId = $("start-part-select").value;
  const img = $("start-preview");
  img.alt = partId || "";
  img.dataset.partId = partId || "";
  if (!partId) {
    img.removeAttribute("src");
    return;
  }
  const url = await thumbnails.draw(partId, colourOf(0));
  if ($("start-part-select").value === partId) img.src = url;
}

function turnPage(step) {
  const offset = picker.offset + step * START_PAGE;
  if (offset < 0 || offset >= picker.total) return undefined;
  picker.offset = offset;
  return busy("Loading parts", loadStartParts);
}

async function chooseCategory() {
  state.category = $("category-select").value || null;
  picker.offset = 0;
  await loadStartParts();
  await refreshSuggestions();
}

async function startFromPart() {
  const partId = $("start-part-select").value;
  if (!partId) return;
  const rec = await partRecord(partId);
  await edit(() => {
    state.category = rec.category;
    state.cloud = null;
    state.parts = [{ partId, translation: rec.translation, scale: [1, 1, 1], label: rec.label }];
  });
}

// An uploaded mesh is in the designer's own units and axes, and it is only part of an object:
// its own box says nothing about the complete object's. So the service fits the complete
// object's frame (fit_frame: centre, radius, up axis y or z; docs/modeling.md) and the mesh is
// brought from that frame into the canonical one; the up-axis choice keeps the axis the
// designer knows, the rest is fitted. A mesh it cannot fit (no extent) is scaled
// by its own box as before. The upload keeps the category chosen in the dropdown ("Any
// category": none, and the page shows what the service reads from the shape).
async function startFromMesh(file) {
  const geometry = await parseMeshFile(file);
  const category = $("category-select").value || null;
  let frame = null;
  try {
    const raw = sampleSurface(geometry, QUERY_POINTS, 1);
    const up = $("upload-up-axis").value;  // "": the service finds it too
    const fit = await postJson("/suggest", {
      points_base64: floatsToBase64(raw.points), k: 1, fit_frame: true, ...(category ? { category } : {}),
      ...(up ? { frame: { up_axis: up } } : {}),
    });
    frame = fit.frame;
    toCanonical(geometry, frame);
  } catch (err) {
    if (!(err instanceof ApiError) || err.code !== "frame_unfit") throw err;
    normalise(geometry, UPLOAD_RADIUS);
  }
  const { points, area } = sampleSurface(geometry, QUERY_POINTS, 1);
  await edit(() => {
    state.category = category;
    state.parts = [];
    state.cloud = { geometry, points, area, name: file.name, frame };
  });
}

function main() {
  viewer = new Viewer($("viewport"));
  viewer.onPick = pickSpot;
  viewer.onBox = pickBox;
  thumbnails = new Thumbnailer(96);
  $("category-select").addEventListener("change", () => busy("Loading parts", chooseCategory));
  let searchTimer = null;
  $("start-part-search").addEventListener("input", () => {
    clearTimeout(searchTimer);
    searchTimer = setTimeout(() => {
      picker.query = $("start-part-search").value.trim();
      picker.offset = 0;
      busy("Searching parts", loadStartParts);
    }, SEARCH_DELAY_MS);
  });
  $("start-part-select").addEventListener("change", () => busy("Drawing the part", previewStart));
  $("start-part-select").addEventListener("dblclick", () => busy("Starting", startFromPart));
  $("start-prev").addEventListener("click", () => turnPage(-1));
  $("start-next").addEventListener("click", () => turnPage(1));
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
  $("notice-close").addEventListener("click", clearNotice);
  $("clear-spot").addEventListener("click", () => {
    setSpot(null);
    busy("Updating suggestions", refreshSuggestions);
  });
  $("spot-radius").addEventListener("change", () => {
    if (!spot?.point) return;
    setSpot({ ...spot, radius: Number($("spot-radius").value) });
    busy("Finding parts for this spot", refreshSuggestions);
  });
  for (const id of ["diversity-toggle", "refine-toggle"]) {
    $(id).addEventListener("change", () => busy("Updating suggestions", refreshSuggestions));
  }
  renderPartList();
  busy("Loading categories", loadCategories);
}

main();
