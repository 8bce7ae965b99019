// The ground station's web interface: task generation and the module connection view.
// Plain JavaScript served by the station; everything it knows comes from the station's API.
'use strict';

const S = {
  view: 'tasks',
  kinds: {},          // kind name -> spec (ports, message types, params)
  live: null,         // /api/live
  base: null,         // the netlist in force: {revision, doc, text}
  draft: null,        // the netlist document being edited
  draftFile: 'draft.toml',
  task: null,         // the task shown in the editor
  selected: null,     // {type: 'module', name} | {type: 'link', index}
  check: null,        // the last check of the draft
  checkSeq: 0,
  checkTimer: null,
  drag: null,         // a link being drawn
  layout: null,       // where every module and port is drawn
  watch: null,        // the watched output
  outbox: [],
  seqFile: null,      // the sequence file read into the text area: {file, name}
  seen: {},           // module -> {restarts, hangs} at the last poll
  sticky: {},         // module -> {state, until, note}: a failure stays visible a while
  perf: { renders: [], checks: [], firstDraftMs: 0, longTasks: [], events: [] },
};
window.__dnm = S;

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c]));

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  };
  const r = await fetch(path, init);
  let j = null;
  try { j = await r.json(); } catch (_) { /* not JSON */ }
  if (!r.ok) throw new Error((j && j.error) || `${path}: HTTP ${r.status}`);
  return j;
}

function say(text, kind) {
  const m = $('message');
  m.textContent = text;
  m.title = text;
  m.className = kind || '';
  m.dataset.kind = kind || '';
}

// ---- the draft ------------------------------------------------------------------------------

function modules() { return (S.draft && S.draft.module) || []; }
function dnms() { return (S.draft && S.draft.dnm) || []; }
function tasks() { return (S.draft && S.draft.task) || {}; }
function moduleByName(n) { return modules().find((m) => m.name === n); }
function kindOf(n) { const m = moduleByName(n); return m ? S.kinds[m.kind] : null; }
function dnmOf(m) { return m.dnm || (dnms()[0] && dnms()[0].name) || '(no DNM)'; }

function parseLink(s) {
  const m = /^\s*([\w-]+)\.([\w-]+)\s*->\s*([\w-]+)\.([\w-]+)\s*$/.exec(s);
  return m ? { from: { module: m[1], port: m[2] }, to: { module: m[3], port: m[4] } } : null;
}
function linkText(l) { return `${l.from.module}.${l.from.port} -> ${l.to.module}.${l.to.port}`; }

function portSpec(module, port, dir) {
  const k = kindOf(module);
  if (!k) return null;
  return (dir === 'out' ? k.outputs : k.inputs).find((p) => p.name === port) || null;
}

function typeText(t) {
  if (!t) return 'an unknown type';
  const p = t.payload || {};
  return p.layout === 'fixed' ? `${t.schema_name} (${p.size_bytes} B)` : `${t.schema_name} (bytes)`;
}

// Two ports may be linked when the producer's type is the consumer's (as `dnm check` says).
function compatible(a, b) {
  if (!a || !b) return false;
  if (a.schema_name !== b.schema_name || a.encoding !== b.encoding) return false;
  const pa = a.payload || {}, pb = b.payload || {};
  if (pa.layout !== pb.layout) return false;
  return pa.layout !== 'fixed' || pa.size_bytes === pb.size_bytes;
}

function changed(what) {
  if (what) say(what, 'ok');
  scheduleCheck();
  render();
}

function scheduleCheck() {
  clearTimeout(S.checkTimer);
  // A check still on its way is of an older draft: its answer must not enable Apply.
  S.checkSeq++;
  $('check-state').className = 'pending';
  $('check-state').textContent = 'checking…';
  $('draft-apply').disabled = true;
  S.checkTimer = setTimeout(runCheck, 200);
}

async function runCheck() {
  const seq = ++S.checkSeq;
  const t0 = performance.now();
  try {
    const c = await api('/api/check', { file: S.draftFile, doc: S.draft });
    if (seq !== S.checkSeq) return;
    S.perf.checks.push(performance.now() - t0);
    S.check = c;
    const st = $('check-state');
    st.className = c.ok ? 'ok' : 'bad';
    st.textContent = c.ok ? 'valid' : `${c.errors.length} problem${c.errors.length === 1 ? '' : 's'}`;
    $('draft-apply').disabled = !c.ok;
    $('problems').innerHTML = c.errors.map((e) =>
      `<li><span class="where">${e.line ? `line ${esc(e.line)}` : ''}${e.field ? ` ${esc(e.field)}` : ''}</span>: ${esc(e.message)}${e.help ? ` <i>(${esc(e.help)})</i>` : ''}</li>`).join('');
  } catch (e) {
    if (seq !== S.checkSeq) return;
    S.check = null;
    $('check-state').className = 'bad';
    $('check-state').textContent = 'cannot check';
    $('problems').innerHTML = `<li>${esc(e.message)}</li>`;
    // The station or the rover's kinds were not there yet: the same draft is checked again.
    S.checkTimer = setTimeout(runCheck, 2000);
  }
}

// An operator's link from an output to an input: refused with the reason when it cannot be.
function tryLink(from, to) {
  const t = tasks()[S.task];
  if (!t) { say('create a task first', 'refused'); return false; }
  const out = portSpec(from.module, from.port, 'out');
  const inp = portSpec(to.module, to.port, 'in');
  if (!out || !inp) { say(`refused: ${from.module}.${from.port} or ${to.module}.${to.port} is not a port of its kind`, 'refused'); return false; }
  if (!compatible(out.message, inp.message)) {
    say(`refused: ${from.module}.${from.port} sends ${typeText(out.message)} but ${to.module}.${to.port} takes ${typeText(inp.message)}`, 'refused');
    return false;
  }
  t.links = t.links || [];
  const fed = t.links.map(parseLink).find((l) => l && l.to.module === to.module && l.to.port === to.port);
  if (fed) {
    say(`refused: ${to.module}.${to.port} is already fed by ${fed.from.module}.${fed.from.port} in task ${S.task}; remove that link first`, 'refused');
    return false;
  }
  const text = linkText({ from, to });
  t.links.push(text);
  changed(`linked ${text} in task ${S.task}`);
  return true;
}

// As the netlist's own rule says: a letter, then letters, digits, `_` or `-`; 48 at most.
const NAME = /^[A-Za-z][A-Za-z0-9_-]{0,47}$/;

function uniqueName(base, taken) {
  let n = base, i = 2;
  while (taken(n)) n = `${base}_${i++}`;
  return n;
}

function taskAction(action) {
  const name = $('task-name').value.trim();
  const all = tasks();
  const valid = NAME.test(name);
  if (action !== 'delete' && !valid) { say('type a task name first: a letter, then letters, digits, _ or - (48 at most)', 'refused'); return; }
  if (action !== 'delete' && all[name]) { say(`task ${name} exists already`, 'refused'); return; }
  S.draft.task = all;
  S.selected = null;
  if (action === 'new') {
    all[name] = { description: 'composed in the ground station', links: [] };
    S.task = name;
    changed(`task ${name} created: draw its links`);
  } else if (action === 'copy') {
    if (!all[S.task]) return;
    all[name] = JSON.parse(JSON.stringify(all[S.task]));
    S.task = name;
    changed(`task ${name} copied`);
  } else if (action === 'rename') {
    if (!all[S.task]) return;
    all[name] = all[S.task];
    delete all[S.task];
    const sys = S.draft.system || {};
    if (sys.default_task === S.task) sys.default_task = name;
    if (sys.on_link_loss && sys.on_link_loss.task === S.task) sys.on_link_loss.task = name;
    S.task = name;
    changed(`task renamed to ${name}`);
  } else if (action === 'delete') {
    if (!all[S.task]) return;
    const gone = S.task;
    delete all[gone];
    S.task = Object.keys(all)[0] || null;
    changed(`task ${gone} deleted`);
  }
  $('task-name').value = '';
  fillTaskSelect();
}

function addModule(kind) {
  const dnm = $('add-dnm').value;
  const name = uniqueName(kind, (n) => !!moduleByName(n));
  S.draft.module = modules();
  S.draft.module.push({ name, kind, dnm });
  S.selected = { type: 'module', name };
  changed(`module ${name} (${kind}) added on ${dnm}`);
}

function forEachTask(fn) { for (const [name, t] of Object.entries(tasks())) fn(name, t); }

function removeModule(name) {
  S.draft.module = modules().filter((m) => m.name !== name);
  let dropped = 0;
  forEachTask((_, t) => {
    const before = (t.links || []).length;
    t.links = (t.links || []).filter((s) => { const l = parseLink(s); return !l || (l.from.module !== name && l.to.module !== name); });
    dropped += before - t.links.length;
  });
  S.selected = null;
  changed(`module ${name} removed with ${dropped} link${dropped === 1 ? '' : 's'}`);
}

function renameModule(old, name) {
  if (!NAME.test(name)) { say(`${name}: a module name is a letter, then letters, digits, _ or - (48 at most)`, 'refused'); return; }
  if (moduleByName(name)) { say(`a module ${name} exists already`, 'refused'); return; }
  moduleByName(old).name = name;
  forEachTask((_, t) => {
    t.links = (t.links || []).map((s) => {
      const l = parseLink(s);
      if (!l) return s;
      if (l.from.module === old) l.from.module = name;
      if (l.to.module === old) l.to.module = name;
      return linkText(l);
    });
  });
  S.selected = { type: 'module', name };
  changed(`module ${old} renamed ${name}`);
}

// Another kind for a module: links to ports the new kind lacks (or types it changes) go.
function replaceKind(name, kind) {
  const m = moduleByName(name);
  m.kind = kind;
  const k = S.kinds[kind];
  if (m.params) for (const p of Object.keys(m.params)) if (!k.params.some((q) => q.name === p)) delete m.params[p];
  let dropped = 0;
  forEachTask((_, t) => {
    const before = (t.links || []).length;
    t.links = (t.links || []).filter((s) => {
      const l = parseLink(s);
      if (!l || (l.from.module !== name && l.to.module !== name)) return true;
      const out = portSpec(l.from.module, l.from.port, 'out');
      const inp = portSpec(l.to.module, l.to.port, 'in');
      return out && inp && compatible(out.message, inp.message);
    });
    dropped += before - t.links.length;
  });
  changed(`module ${name} replaced by a ${kind}${dropped ? `; ${dropped} link${dropped === 1 ? '' : 's'} it cannot keep removed` : ''}`);
}

function setParam(name, p, raw) {
  const m = moduleByName(name);
  m.params = m.params || {};
  const text = typeof raw === 'string' && p.kind !== 'string' ? raw.trim() : raw;
  if (text === '' || text === null) { delete m.params[p.name]; changed(`${name}.${p.name} back to its default`); return; }
  let v = text;
  if (p.kind === 'float') v = /^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$/.test(text) ? Number(text) : NaN;
  else if (p.kind === 'int') v = /^[-+]?\d{1,15}$/.test(text) ? Number(text) : NaN;
  else if (p.kind === 'bool') v = text === true || text === 'true';
  if ((p.kind === 'float' || p.kind === 'int') && !Number.isFinite(v)) {
    m.params[p.name] = text; // kept as text: the check names the field and the fix
  } else {
    m.params[p.name] = v;
  }
  changed(`${name}.${p.name} = ${JSON.stringify(m.params[p.name])}`);
}

// ---- layout and drawing -----------------------------------------------------------------------
//
// Laid out by data flow: a module's column is its depth along the links of every task (sources
// on the left, sinks on the right; the same place whatever task is in force), each DNM a lane
// across the columns, in hierarchy order. Links run on tracks of their own: out of a module's
// right side into the channel after its column, along the corridor under its lane when they skip
// columns or go back, and into the left side of their target from the channel before its
// column. Channels and corridors hold no module, so no link crosses a box; each output's rate
// label sits on its own stub, beside the box.

const BOX_W = 200, ROW_H = 15, HEAD_H = 34, GAP = 12, LEFT = 12, LANE_HEAD = 40, LANE_GAP = 14;
// Track spacing, the narrowest channel (room for a rate label), the corridor's margin.
const TRACK = 7, LABEL_W = 96, EDGE = 10;

// DNMs in hierarchy order: each after its parent.
function dnmOrder(list) {
  const names = list.map((d) => d.name);
  const out = [];
  const visit = (parent, depth) => {
    for (const d of list) {
      if ((d.parent || null) === parent && !out.some((o) => o.name === d.name)) {
        out.push({ ...d, depth });
        visit(d.name, depth + 1);
      }
    }
  };
  visit(null, 0);
  for (const d of list) if (!out.some((o) => o.name === d.name)) out.push({ ...d, depth: 0, orphan: !names.includes(d.parent) });
  return out;
}

// Each module's column: the longest chain of links leading to it (links closing a cycle left
// out), a source pulled right next to the first module it feeds.
function ranks(names, edges) {
  const succ = Object.fromEntries(names.map((n) => [n, []]));
  const preds = Object.fromEntries(names.map((n) => [n, 0]));
  for (const [a, b] of edges) if (succ[a] && succ[b] && a !== b && !succ[a].includes(b)) succ[a].push(b);
  const state = {}, order = [], back = new Set();
  const visit = (n) => {
    state[n] = 1;
    for (const s of succ[n]) {
      if (state[s] === 1) back.add(`${n}\u0000${s}`);
      else if (!state[s]) visit(s);
    }
    state[n] = 2;
    order.push(n);
  };
  // From the sources first: a cycle is then cut where it closes, not where the declaration
  // order happens to enter it.
  const fed = new Set(Object.values(succ).flat());
  for (const n of names) if (!state[n] && !fed.has(n)) visit(n);
  for (const n of names) if (!state[n]) visit(n);
  order.reverse();
  const forward = (a) => succ[a].filter((b) => !back.has(`${a}\u0000${b}`));
  for (const a of names) for (const b of forward(a)) preds[b] += 1;
  const rank = Object.fromEntries(names.map((n) => [n, 0]));
  for (const a of order) for (const b of forward(a)) rank[b] = Math.max(rank[b], rank[a] + 1);
  for (const a of [...order].reverse()) {
    const next = forward(a);
    if (preds[a] === 0 && next.length) rank[a] = Math.max(0, Math.min(...next.map((b) => rank[b])) - 1);
  }
  return rank;
}

// mods: [{name, kind, dnm, inputs:[port], outputs:[port]}]; links: [{from:{module,port}, to:{module,port}}]
// drawn (their routes in L.routes, in order); every task's module pairs in `all` set the columns.
function layout(dnmList, mods, links, all) {
  const declared = new Set(dnmList.map((d) => d.name));
  const extra = [...new Set(mods.map((m) => m.dnm).filter((d) => !declared.has(d)))].map((name) => ({ name, undeclared: true }));
  const lanes = dnmOrder(dnmList.concat(extra));
  const byName = Object.fromEntries(mods.map((m) => [m.name, m]));
  const rank = ranks(mods.map((m) => m.name), all.filter(([a, b]) => byName[a] && byName[b]));
  const ncol = 1 + Math.max(0, ...Object.values(rank));
  const drawn = links.filter((l) => byName[l.from.module] && byName[l.to.module]
    && byName[l.from.module].outputs.some((p) => p.name === l.from.port)
    && byName[l.to.module].inputs.some((p) => p.name === l.to.port));
  const adjacent = (l) => rank[l.to.module] === rank[l.from.module] + 1;
  // Tracks: per channel (-1: before the first column) and per lane's corridor.
  const chan = {}, corridor = {};
  const take = (table, key, id) => { (table[key] = table[key] || []).includes(id) || table[key].push(id); };
  const laneOf = (m) => lanes.findIndex((d) => d.name === byName[m].dnm);
  drawn.forEach((l, i) => {
    take(chan, rank[l.from.module], `out:${l.from.module}.${l.from.port}`);
    if (!adjacent(l)) {
      take(chan, rank[l.to.module] - 1, `link:${i}`);
      take(corridor, laneOf(l.from.module), `link:${i}`);
    }
  });
  const width = (c) => Math.max(c < 0 ? 2 * EDGE : LABEL_W, 2 * EDGE + ((chan[c] || []).length) * TRACK);
  const colX = [];
  let x = LEFT + width(-1);
  for (let c = 0; c < ncol; c++) { colX.push(x); x += BOX_W + width(c); }
  const chanX = (c) => (c < 0 ? LEFT : colX[c] + BOX_W);
  // Boxes: per lane and column, stacked; in a column, ordered by where what feeds them sits.
  const at = {}, ports = {};
  const feeds = {};
  for (const [a, b] of all) if (byName[a] && byName[b]) (feeds[b] = feeds[b] || []).push(a);
  const place = {};
  let y = 6;
  lanes.forEach((d, li) => {
    d.top = y;
    let bottom = y + LANE_HEAD;
    for (let c = 0; c < ncol; c++) {
      const cell = mods.filter((m) => m.dnm === d.name && rank[m.name] === c);
      const bary = (m) => {
        const ys = (feeds[m.name] || []).filter((f) => place[f] != null).map((f) => place[f]);
        return ys.length ? ys.reduce((s, v) => s + v, 0) / ys.length : Infinity;
      };
      cell.sort((a, b) => bary(a) - bary(b) || (mods.indexOf(a) - mods.indexOf(b)));
      let yy = y + LANE_HEAD;
      for (const m of cell) {
        const rows = Math.max(m.inputs.length, m.outputs.length, 1);
        const h = HEAD_H + rows * ROW_H + 6;
        at[m.name] = { x: colX[c], y: yy, h, m };
        place[m.name] = yy + h / 2;
        m.inputs.forEach((p, j) => { ports[`in:${m.name}.${p.name}`] = { x: colX[c], y: yy + HEAD_H + j * ROW_H + 6 }; });
        m.outputs.forEach((p, j) => { ports[`out:${m.name}.${p.name}`] = { x: colX[c] + BOX_W, y: yy + HEAD_H + j * ROW_H + 6 }; });
        yy += h + GAP;
      }
      bottom = Math.max(bottom, yy - GAP + EDGE);
    }
    d.bottom = bottom;
    d.corridor = bottom;
    y = bottom + Math.max(LANE_GAP, 2 * EDGE + ((corridor[li] || []).length) * TRACK);
  });
  // Routes: a polyline per drawn link, on its tracks.
  const trackX = (c, id) => chanX(c) + EDGE + (chan[c].indexOf(id) + 0.5) * TRACK;
  const routes = drawn.map((l, i) => {
    const a = ports[`out:${l.from.module}.${l.from.port}`], b = ports[`in:${l.to.module}.${l.to.port}`];
    const t1 = trackX(rank[l.from.module], `out:${l.from.module}.${l.from.port}`);
    if (adjacent(l)) return { link: l, points: [[a.x, a.y], [t1, a.y], [t1, b.y], [b.x, b.y]] };
    const li = laneOf(l.from.module);
    const yc = lanes[li].corridor + EDGE + (corridor[li].indexOf(`link:${i}`) + 0.5) * TRACK;
    const t2 = trackX(rank[l.to.module] - 1, `link:${i}`);
    return { link: l, points: [[a.x, a.y], [t1, a.y], [t1, yc], [t2, yc], [t2, b.y], [b.x, b.y]] };
  });
  return { lanes, at, ports, routes, width: x + LEFT, height: y + 6 };
}

function polyline(points) {
  return 'M' + points.map(([px, py]) => `${px.toFixed(1)},${py.toFixed(1)}`).join(' L');
}

// The drawing line while a link is drawn.
function curve(a, b) {
  const dx = Math.max(40, Math.abs(b.x - a.x) / 2);
  return `M${a.x},${a.y} C${a.x + dx},${a.y} ${b.x - dx},${b.y} ${b.x},${b.y}`;
}

// Every task's module-level links: what the columns are made of.
function taskPairs(taskLinks) {
  const out = [];
  for (const l of taskLinks) if (l) out.push([l.from.module, l.to.module]);
  return out;
}

function drawColumns(L) {
  return L.lanes.map((d) => `<g class="dnm-col"><rect class="col" x="4" y="${d.top}" width="${L.width - 8}" height="${d.bottom - d.top}" rx="6"/>`
    + `<text class="col-title" x="12" y="${d.top + 16}">${'↳ '.repeat(d.depth ? 1 : 0)}${esc(d.name)}</text>`
    + `<text class="col-sub" x="12" y="${d.top + 30}">${d.undeclared ? 'not declared: add it to [[dnm]]' : d.parent ? `under ${esc(d.parent)}` : 'root'}${d.radio ? ' · across the radio' : ''}</text></g>`).join('');
}

function drawModule(box, cls, lines) {
  const m = box.m;
  let s = `<g class="module ${cls}" data-module="${esc(m.name)}"><rect class="box" x="${box.x}" y="${box.y}" width="${BOX_W}" height="${box.h}"/>`
    + `<rect class="head" x="${box.x}" y="${box.y}" width="${BOX_W}" height="${HEAD_H - 4}"/>`
    + `<text class="title" x="${box.x + 6}" y="${box.y + 13}">${esc(m.name)}</text>`
    + `<text class="kind" x="${box.x + 6}" y="${box.y + 26}">${esc(lines)}</text>`;
  m.inputs.forEach((p, j) => {
    const y = box.y + HEAD_H + j * ROW_H + 6;
    s += `<circle class="port in" r="5" cx="${box.x}" cy="${y}" data-port="${esc(m.name)}.${esc(p.name)}" data-dir="in"><title>${esc(p.name)}: ${esc(typeText(p.message))}</title></circle>`
      + `<text x="${box.x + 8}" y="${y + 4}">${esc(p.name)}</text>`;
  });
  m.outputs.forEach((p, j) => {
    const y = box.y + HEAD_H + j * ROW_H + 6;
    s += `<circle class="port out" r="5" cx="${box.x + BOX_W}" cy="${y}" data-port="${esc(m.name)}.${esc(p.name)}" data-dir="out"><title>${esc(p.name)}: ${esc(typeText(p.message))}</title></circle>`
      + `<text x="${box.x + BOX_W - 8}" y="${y + 4}" text-anchor="end">${esc(p.name)}</text>`;
  });
  return s + '</g>';
}

function draftModules() {
  return modules().map((m) => {
    const k = S.kinds[m.kind];
    return { name: m.name, kind: m.kind, dnm: dnmOf(m), inputs: k ? k.inputs : [], outputs: k ? k.outputs : [] };
  });
}

function renderTasks() {
  if (!S.draft) return;
  const mods = draftModules();
  const t = tasks()[S.task];
  const parsed = ((t && t.links) || []).map(parseLink);
  const every = Object.values(tasks()).flatMap((tk) => (tk.links || []).map(parseLink));
  const shown = parsed.map((l, i) => (l ? { ...l, index: i } : null)).filter(Boolean);
  const L = layout(dnms(), mods, shown, taskPairs(every));
  S.layout = L;
  let links = '';
  for (const r of L.routes) {
    const i = r.link.index;
    const sel = S.selected && S.selected.type === 'link' && S.selected.index === i;
    links += `<path class="link${sel ? ' selected' : ''}" d="${polyline(r.points)}" data-link="${i}"><title>${esc(t.links[i])}</title></path>`;
  }
  let boxes = '';
  for (const m of mods) {
    const k = S.kinds[m.kind];
    const sel = S.selected && S.selected.type === 'module' && S.selected.name === m.name;
    if (L.at[m.name]) boxes += drawModule(L.at[m.name], `draft${sel ? ' selected' : ''}`, k ? m.kind : `${m.kind} (not on the rover)`);
  }
  const svg = $('canvas');
  svg.setAttribute('width', L.width);
  svg.setAttribute('height', L.height);
  svg.innerHTML = drawColumns(L) + `<g id="links">${links}</g>` + boxes + '<path id="drag-line" d=""/>';
  renderInspector();
}

function stateOf(name, dnm) {
  const g = S.live && S.live.live.glances[dnm];
  const m = g && g.modules.find((x) => x.name === name);
  return m || null;
}

// How long a failure or hang stays shown after the module is back: a restart takes 100 ms,
// less than a poll, and an operator must still see that it happened.
const STICKY_MS = 4000;

// Notes failures and hangs, including those that came and went between two polls (the
// restart or hang count went up).
function noteFailures() {
  const now = Date.now();
  for (const g of Object.values(S.live.live.glances)) {
    for (const m of g.modules) {
      const prev = S.seen[m.name];
      let state = null, note = '';
      if (m.state === 'failed' || m.state === 'hung') state = m.state;
      else if (prev && m.hangs > prev.hangs) { state = 'hung'; note = 'recovered'; }
      else if (prev && m.restarts > prev.restarts) { state = 'failed'; note = 'restarted'; }
      if (state) S.sticky[m.name] = { state, until: now + STICKY_MS, note };
      S.seen[m.name] = { restarts: m.restarts, hangs: m.hangs };
    }
  }
}

function shownState(name, st) {
  const s = S.sticky[name];
  if (s && s.until > Date.now() && st && st.state !== 'failed' && st.state !== 'hung') return s;
  return st ? { state: st.state, note: '' } : { state: 'unknown', note: '' };
}

function renderConnections() {
  const w = S.live && S.live.live.wiring;
  const svg = $('canvas');
  if (!w) { svg.innerHTML = '<text x="20" y="30">No wiring heard from the rover yet.</text>'; return; }
  const mods = w.modules.map((m) => ({ name: m.name, kind: m.kind, dnm: m.dnm, inputs: m.inputs, outputs: m.outputs }));
  const active = (w.active_task && w.tasks[w.active_task]) || [];
  const L = layout(w.dnms, mods, active, taskPairs(Object.values(w.tasks).flat()));
  S.layout = L;
  const radio = Object.fromEntries(w.dnms.map((d) => [d.name, !!d.radio]));
  const dnmOfMod = Object.fromEntries(w.modules.map((m) => [m.name, m.dnm]));
  let links = '';
  // One label per output that feeds something: its rate, and whether it crosses the radio.
  const labels = {};
  for (const r of L.routes) {
    const l = r.link;
    const da = dnmOfMod[l.from.module], db = dnmOfMod[l.to.module];
    const crossesRadio = da !== db && (radio[da] || radio[db]);
    const src = stateOf(l.from.module, da);
    const hz = src ? src.rate_hz : 0;
    const srcMod = w.modules.find((m) => m.name === l.from.module);
    const outPort = srcMod && srcMod.outputs.find((p) => p.name === l.from.port);
    const size = outPort && outPort.message.payload.layout === 'fixed' ? outPort.message.payload.size_bytes : null;
    const traffic = size == null ? '' : `, ~${(hz * size / 1000).toFixed(1)} kB/s`;
    const text = `${l.from.module}.${l.from.port} -> ${l.to.module}.${l.to.port}`;
    links += `<path class="link${crossesRadio ? ' radio' : ''}" d="${polyline(r.points)}" style="stroke-width:${(1.2 + Math.min(4, Math.log10(1 + hz))).toFixed(1)}" data-active-link="${esc(text)}" data-radio="${crossesRadio ? 1 : 0}"><title>${esc(text)}: ${hz.toFixed(1)} Hz${traffic}${crossesRadio ? ', across the radio' : ''}</title></path>`;
    const key = `${l.from.module}.${l.from.port}`;
    const [px, py] = r.points[0];
    labels[key] = { x: px + 6, y: py - 3, hz, radio: (labels[key] && labels[key].radio) || crossesRadio };
  }
  for (const [port, lb] of Object.entries(labels)) {
    links += `<text class="link-label${lb.radio ? ' radio' : ''}" x="${lb.x}" y="${lb.y}" data-label-of="${esc(port)}">${lb.hz.toFixed(0)} Hz${lb.radio ? ' · radio' : ''}</text>`;
  }
  let boxes = '';
  let counts = {};
  for (const m of mods) {
    const st = stateOf(m.name, m.dnm);
    const shown = shownState(m.name, st);
    const state = shown.state;
    counts[state] = (counts[state] || 0) + 1;
    const line = st ? `${shown.note ? `${shown.note} · ` : ''}${m.kind} · ${st.rate_hz.toFixed(1)} Hz · ${st.cpu_percent.toFixed(1)}% CPU${st.restarts ? ` · ${st.restarts} restart${st.restarts === 1 ? '' : 's'}` : ''}${st.hangs ? ` · hung ${st.hangs}×` : ''}` : `${m.kind} · no answer`;
    if (L.at[m.name]) boxes += drawModule(L.at[m.name], state, line).replace('<g class="module', `<g data-state="${esc(state)}" data-restarts="${esc(st ? st.restarts : 0)}" class="module`);
  }
  svg.setAttribute('width', L.width);
  svg.setAttribute('height', L.height);
  svg.innerHTML = drawColumns(L) + links + boxes;
  const age = S.live.live.age_ms;
  $('conn-summary').textContent = (age == null || age > 3000 ? `AS OF ${age == null ? '—' : (age / 1000).toFixed(0) + ' s'} AGO · ` : '')
    + `revision ${w.revision} · task ${w.active_task || '—'} · ${mods.length} modules: `
    + Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(', ')
    + (S.live.live.silent.length ? ` · silent DNMs: ${S.live.live.silent.join(', ')}` : '');
}

function renderHierarchy() {
  const w = S.live && S.live.live.wiring;
  if (!w) return;
  const silent = new Set(S.live.live.silent);
  const tree = (parent) => w.dnms.filter((d) => (d.parent || null) === parent).map((d) => {
    const g = S.live.live.glances[d.name];
    const n = w.modules.filter((m) => m.dnm === d.name).length;
    return `<li class="${silent.has(d.name) ? 'silent' : ''}" data-dnm="${esc(d.name)}">${esc(d.name)}${d.radio ? ' (radio)' : ''} · ${n} modules${g ? ` · rev ${esc(g.revision)} · ${esc(g.active_task || '—')}` : ' · silent'}<ul>${tree(d.name)}</ul></li>`;
  }).join('');
  $('hierarchy').innerHTML = tree(null);
  const l = S.live.link;
  const rover = l.rover || {};
  $('link-detail').innerHTML = [
    ['state', l.up ? 'up' : 'down'],
    ['round trip', l.rtt_ms == null ? '—' : `${l.rtt_ms.toFixed(0)} ms`],
    ['last heard', l.last_contact_ms == null ? 'never' : `${(l.last_contact_ms / 1000).toFixed(1)} s ago`],
    ['loss', `${(100 * l.loss).toFixed(0)} %`],
    ['pending', String(l.pending)],
    ['rover task', rover.task || '—'],
    ['revision', rover.revision == null ? '—' : String(rover.revision)],
    ['safe', rover.safe && rover.last_safing
      ? `since ${new Date(rover.last_safing.at_unix_ns / 1e6).toLocaleTimeString()}: ${rover.last_safing.reason} (commands given before the station saw it are refused)`
      : 'no'],
  ].map(([k, v]) => `<dt>${k}</dt><dd>${esc(v)}</dd>`).join('');
  // What the station commanded (wall time), the switches the DNMs performed (each DNM's own
  // clock: grouped, not timed) and the last module events.
  const commanded = S.outbox.filter((e) => e.order.cmd !== 'cancel').slice(-12).reverse().map((e) => {
    const o = e.order;
    const f = e.fate || {};
    return `<li>${new Date(e.queued_unix_ns / 1e6).toLocaleTimeString()} #${esc(e.seq)} ${esc(orderText(o))}: <span class="state ${esc(e.state)}">${esc(e.state)}</span>${f.revision ? ` rev ${esc(f.revision)}` : ''}${f.reason ? ` — <span class="reason">${esc(f.reason)}</span>` : ''}</li>`;
  });
  const switches = new Map();
  for (const g of Object.values(S.live.live.glances)) {
    for (const s of g.switches || []) {
      const key = `${s.revision}:${s.from || ''}:${s.to}`;
      const e = switches.get(key) || { s, dnms: [], at: s.at_ns };
      e.dnms.push(g.dnm);
      switches.set(key, e);
    }
  }
  const performed = [...switches.values()].sort((a, b) => b.s.revision - a.s.revision || b.at - a.at).slice(0, 12)
    .map((e) => `<li class="switch">rev ${esc(e.s.revision)}: ${esc(e.s.from || '—')} → <b>${esc(e.s.to)}</b> on ${esc(e.dnms.sort().join(', '))}</li>`);
  const events = [];
  for (const g of Object.values(S.live.live.glances)) for (const e of g.events || []) events.push(e);
  events.sort((a, b) => b.at_ns - a.at_ns);
  const evs = events.slice(0, 16).map((e) => `<li class="event">${esc(e.dnm)}: ${esc(e.module)} ${esc(e.what)}${e.detail ? ` (${esc(e.detail)})` : ''}</li>`);
  $('history').innerHTML = `<li><h2>Commanded</h2><ol>${commanded.join('') || '<li class="hint">nothing yet</li>'}</ol></li>`
    + `<li><h2>Switches performed</h2><ol>${performed.join('') || '<li class="hint">none yet</li>'}</ol></li>`
    + `<li><h2>Module events</h2><ol>${evs.join('') || '<li class="hint">none</li>'}</ol></li>`;
}

function renderInspector() {
  const body = $('inspector-body');
  if (!S.draft) return;
  if (S.selected && S.selected.type === 'module' && moduleByName(S.selected.name)) {
    const m = moduleByName(S.selected.name);
    const k = S.kinds[m.kind];
    const kinds = Object.keys(S.kinds).sort();
    let h = `<div class="field"><span>name</span><input id="mod-name" value="${esc(m.name)}"></div>`
      + `<div class="field"><span>kind</span><select id="mod-kind">${kinds.map((n) => `<option${n === m.kind ? ' selected' : ''}>${esc(n)}</option>`).join('')}</select></div>`
      + `<div class="field"><span>DNM</span><select id="mod-dnm">${dnms().map((d) => `<option${d.name === dnmOf(m) ? ' selected' : ''}>${esc(d.name)}</option>`).join('')}</select></div>`;
    if (k) {
      h += '<h2>Parameters</h2>';
      for (const p of k.params) {
        const v = m.params && p.name in m.params ? m.params[p.name] : '';
        const def = p.default == null ? 'required' : `default ${p.default}`;
        h += p.kind === 'bool'
          ? `<div class="field"><span title="${esc(p.doc)}">${esc(p.name)}</span><select data-param="${esc(p.name)}"><option value=""${v === '' ? ' selected' : ''}>(${esc(def)})</option><option${v === true ? ' selected' : ''}>true</option><option${v === false ? ' selected' : ''}>false</option></select></div>`
          : `<div class="field"><span title="${esc(p.doc)}">${esc(p.name)}</span><input data-param="${esc(p.name)}" value="${esc(v)}" placeholder="${esc(p.kind)}, ${esc(def)}"></div>`;
      }
    }
    h += `<p><button id="mod-remove">Remove module</button></p>`;
    body.innerHTML = h;
    $('mod-name').onchange = (e) => renameModule(m.name, e.target.value.trim());
    $('mod-kind').onchange = (e) => replaceKind(m.name, e.target.value);
    $('mod-dnm').onchange = (e) => { m.dnm = e.target.value; changed(`module ${m.name} moved to ${m.dnm}`); };
    $('mod-remove').onclick = () => removeModule(m.name);
    body.querySelectorAll('[data-param]').forEach((el) => {
      el.onchange = () => setParam(m.name, k.params.find((p) => p.name === el.dataset.param), el.value);
    });
    return;
  }
  const t = tasks()[S.task];
  const links = (t && t.links) || [];
  body.innerHTML = `<p class="hint">Drag from an output (right) to an input (left) to link them. Click a module to edit it.</p>`
    + `<h2>Links of ${esc(S.task || '—')} (${links.length})</h2><ul class="links-list">`
    + links.map((s, i) => `<li class="${S.selected && S.selected.type === 'link' && S.selected.index === i ? 'selected' : ''}"><span>${esc(s)}</span><button data-unlink="${i}" title="remove this link">×</button></li>`).join('')
    + '</ul>';
  body.querySelectorAll('[data-unlink]').forEach((b) => {
    b.onclick = () => {
      const i = Number(b.dataset.unlink);
      const [gone] = t.links.splice(i, 1);
      S.selected = null;
      changed(`link ${gone} removed`);
    };
  });
}

function render() {
  const t0 = performance.now();
  if (S.view === 'tasks') renderTasks(); else { renderConnections(); renderHierarchy(); }
  const ms = performance.now() - t0;
  S.perf.renders.push({ view: S.view, ms });
  if (S.perf.renders.length > 200) S.perf.renders.shift();
}

function fillTaskSelect() {
  const sel = $('task-select');
  const names = Object.keys(tasks());
  if (!names.includes(S.task)) S.task = names[0] || null;
  const active = S.live && S.live.live.wiring && S.live.live.wiring.active_task;
  sel.innerHTML = names.map((n) => `<option value="${esc(n)}"${n === S.task ? ' selected' : ''}>${esc(n)}${n === active ? ' (in force)' : ''}</option>`).join('');
}

function fillPalette() {
  const names = Object.keys(S.kinds).sort();
  const ports = (ps) => ps.map((p) => esc(p.name)).join(', ') || '—';
  $('palette').innerHTML = names.map((n) => {
    const k = S.kinds[n];
    return `<li data-kind="${esc(n)}"><button data-add="${esc(n)}" title="add a ${esc(n)} module">+</button><span class="name">${esc(n)}</span><div class="ports">in: ${ports(k.inputs)}<br>out: ${ports(k.outputs)}${k.params.length ? `<br>params: ${k.params.map((p) => `${esc(p.name)} (${esc(p.kind)})`).join(', ')}` : ''}</div></li>`;
  }).join('');
  $('palette').querySelectorAll('[data-add]').forEach((b) => { b.onclick = () => addModule(b.dataset.add); });
  $('add-dnm').innerHTML = dnms().map((d) => `<option>${esc(d.name)}</option>`).join('');
}

// ---- watching an output -----------------------------------------------------------------------

function flatten(prefix, v, out) {
  if (typeof v === 'number') out.push([prefix, v]);
  else if (typeof v === 'boolean') out.push([prefix, v ? 1 : 0]);
  else if (Array.isArray(v)) v.slice(0, 16).forEach((x, i) => flatten(`${prefix}[${i}]`, x, out));
  else if (v && typeof v === 'object') for (const [k, x] of Object.entries(v)) flatten(prefix ? `${prefix}.${k}` : k, x, out);
}

function startWatch(module, port) {
  S.watch = { module, port, since: 0, samples: [], frame: null, error: null };
  renderWatch();
  pollWatch();
}

async function pollWatch() {
  const w = S.watch;
  if (!w) return;
  try {
    const r = await api(`/api/watch?module=${encodeURIComponent(w.module)}&port=${encodeURIComponent(w.port)}&since=${w.since}`);
    if (S.watch !== w) return;
    w.error = null;
    if (w.id !== r.watch) { w.id = r.watch; w.since = 0; w.samples = []; }
    w.schema = r.schema_name;
    w.rate = r.rate;
    for (const s of r.samples) { w.samples.push(s); w.since = Math.max(w.since, s.seq); }
    if (w.samples.length > 200) w.samples.splice(0, w.samples.length - 200);
    w.frame = r.frame;
  } catch (e) {
    w.error = e.message;
  }
  renderWatch();
  clearTimeout(w.timer);
  w.timer = setTimeout(pollWatch, 500);
}

function spark(values) {
  if (values.length < 2) return '';
  const lo = Math.min(...values), hi = Math.max(...values), span = hi - lo || 1;
  const pts = values.map((v, i) => `${(i / (values.length - 1) * 88 + 1).toFixed(1)},${(17 - (v - lo) / span * 16).toFixed(1)}`).join(' ');
  return `<svg class="spark" viewBox="0 0 90 18"><polyline points="${pts}"/></svg>`;
}

function renderWatch() {
  const w = S.watch;
  const body = $('watch-body');
  if (!w) return;
  let h = `<p><b id="watch-title">${esc(w.module)}.${esc(w.port)}</b> ${w.schema ? `<span class="hint">${esc(w.schema)} at ${esc(w.rate)}</span>` : ''} <button id="watch-stop">stop</button></p>`;
  if (w.error) h += `<p class="hint">${esc(w.error)}</p>`;
  if (w.frame) h += `<img id="watch-frame" alt="camera" src="/api/frame?module=${encodeURIComponent(w.module)}&port=${encodeURIComponent(w.port)}&n=${encodeURIComponent(w.frame)}">`;
  const last = w.samples[w.samples.length - 1];
  if (last) {
    const fields = [];
    flatten('', last.value, fields);
    const series = (f) => w.samples.map((s) => { const o = []; flatten('', s.value, o); const x = o.find((p) => p[0] === f); return x ? x[1] : 0; });
    h += `<p class="hint">${w.samples.length} samples, latest ${new Date(last.unix_ns / 1e6).toLocaleTimeString()}</p><table id="watch-values">`
      + fields.slice(0, 24).map(([f, v], i) => `<tr><td>${esc(f || 'value')}</td><td class="v">${esc(Number.isInteger(v) ? v : Number(v).toFixed(4))}</td><td>${i < 12 ? spark(series(f)) : ''}</td></tr>`).join('')
      + '</table>';
    if (!fields.length) h += `<pre>${esc(JSON.stringify(last.value, null, 1).slice(0, 2000))}</pre>`;
  } else if (!w.frame && !w.error) {
    h += '<p class="hint">waiting for the first sample…</p>';
  }
  body.innerHTML = h;
  $('watch-stop').onclick = () => { clearTimeout(w.timer); S.watch = null; body.innerHTML = '<p class="hint">Click an output port in the connection view to watch it.</p>'; };
}

// ---- pointer: drawing links, selecting ----------------------------------------------------------

function svgPoint(ev) {
  const r = $('canvas').getBoundingClientRect();
  return { x: ev.clientX - r.left, y: ev.clientY - r.top };
}

function markTargets(from) {
  const out = portSpec(from.module, from.port, 'out');
  document.querySelectorAll('.port.in').forEach((c) => {
    const [m, p] = c.dataset.port.split('.');
    const inp = portSpec(m, p, 'in');
    c.classList.add(out && inp && compatible(out.message, inp.message) ? 'compatible' : 'incompatible');
  });
}

function portOf(el) {
  if (!el || !el.dataset || !el.dataset.port) return null;
  const [module, port] = el.dataset.port.split('.');
  return { module, port, dir: el.dataset.dir };
}

function onPointerDown(ev) {
  const p = portOf(ev.target);
  if (S.view === 'connections') {
    if (p && p.dir === 'out') startWatch(p.module, p.port);
    return;
  }
  if (p && p.dir === 'out') {
    ev.preventDefault();
    S.drag = { from: p, start: S.layout.ports[`out:${p.module}.${p.port}`] };
    markTargets(p);
    say(`drawing a link from ${p.module}.${p.port} (${typeText(portSpec(p.module, p.port, 'out').message)}): drop it on an input`, '');
    return;
  }
  if (p && p.dir === 'in') { say('a link starts at an output (the right side of a module)', 'refused'); return; }
  const link = ev.target.closest && ev.target.closest('[data-link]');
  if (link) { S.selected = { type: 'link', index: Number(link.dataset.link) }; say(`link ${tasks()[S.task].links[S.selected.index]} selected: press Delete or × in the list to remove it`, ''); render(); return; }
  const mod = ev.target.closest && ev.target.closest('[data-module]');
  S.selected = mod ? { type: 'module', name: mod.dataset.module } : null;
  render();
}

function onPointerMove(ev) {
  if (!S.drag) return;
  const b = svgPoint(ev);
  const line = $('drag-line');
  if (line) line.setAttribute('d', curve(S.drag.start, b));
}

function onPointerUp(ev) {
  if (!S.drag) return;
  const drag = S.drag;
  S.drag = null;
  const target = portOf(document.elementFromPoint(ev.clientX, ev.clientY));
  if (target && target.dir === 'in') {
    tryLink(drag.from, { module: target.module, port: target.port });
    if ($('message').dataset.kind === 'refused') renderTasks();
  } else {
    say('no link: drop the line on an input port (the left side of a module)', 'refused');
    renderTasks();
  }
}

// ---- onboard sequences --------------------------------------------------------------------------

// The name in a sequence file's `[sequence]` table (what the upload is stored under).
function sequenceName(text) {
  const table = /^\s*\[sequence\]\s*(?:#.*)?$([\s\S]*?)(?=^\s*\[|(?![\s\S]))/m.exec(text);
  if (!table) return null;
  const name = /^\s*name\s*=\s*(?:"((?:[^"\\\n]|\\.)*)"|'([^'\n]*)')/m.exec(table[1]);
  return name ? (name[1] !== undefined ? name[1] : name[2]) : null;
}

// The netlist files a sequence's `apply` steps name, as written.
function appliedFiles(text) {
  return [...text.matchAll(/^\s*apply\s*=\s*(?:"([^"\n]*)"|'([^'\n]*)')/gm)].map((m) => (m[1] !== undefined ? m[1] : m[2]));
}

const baseName = (f) => f.split(/[\\/]/).pop();

// Reads the chosen sequence file into the text area (the operator may edit it before upload).
async function loadSequenceFile() {
  const f = $('seq-file').files[0];
  if (!f) return;
  try {
    const text = await f.text();
    $('seq-text').value = text;
    S.seqFile = { file: f.name, name: sequenceName(text) };
    say(`${f.name} read: upload it to store it on the rover`, 'ok');
  } catch (e) {
    say(`${f.name} could not be read: ${e.message}`, 'refused');
  }
}

// Uploads the sequence in the text area under its `[sequence] name`, with the netlists its
// `apply` steps name (chosen beside it, matched by file name). The rover checks it against the
// netlist in force: a refusal shows its located errors in the outbox and in this panel.
async function uploadSequence() {
  const text = $('seq-text').value;
  const name = sequenceName(text);
  if (!text.trim()) { say('write a sequence or choose its file first', 'refused'); return; }
  if (!name) { say('no name: a sequence file begins with [sequence] and name = "..."', 'refused'); return; }
  const chosen = [...$('seq-netlists').files];
  const netlists = {};
  for (const f of appliedFiles(text)) {
    const file = chosen.find((c) => c.name === baseName(f));
    if (!file) { say(`a step applies ${f}: choose that file in “netlists of its apply steps” first`, 'refused'); return; }
    try { netlists[f] = await file.text(); } catch (e) { say(`${file.name} could not be read: ${e.message}`, 'refused'); return; }
  }
  // Errors are located in the file read, while the text is still that sequence's.
  const file = S.seqFile && S.seqFile.name === name ? S.seqFile.file : `${name}.toml`;
  await submit({ cmd: 'sequence', name, action: { do: 'upload', file, text, netlists } }, `upload of sequence ${name}`);
  renderSequences();
}

// The task in the editor as a step of the sequence being written (a new one if there is none).
function addTaskStep() {
  if (!S.task) { say('choose a task first', 'refused'); return; }
  const area = $('seq-text');
  let text = area.value;
  if (!text.trim()) text = '[sequence]\nname = "plan"\n';
  if (!text.endsWith('\n')) text += '\n';
  if (!text.endsWith('\n\n')) text += '\n';
  area.value = `${text}[[step]]\nswitch = ${JSON.stringify(S.task)}\n`;
  area.scrollTop = area.scrollHeight;
  say(`a switch to ${S.task} added as a step of sequence ${sequenceName(area.value) || '(no name yet)'}`, 'ok');
}

// What an operator may do to a sequence in each state.
const SEQ_ACTIONS = {
  stored: ['start'], running: ['pause', 'cancel'], paused: ['resume', 'cancel'],
  finished: ['start'], aborted: ['start'],
};

function sequenceStep(q) {
  const at = `step ${Math.min(q.step + 1, q.steps)}/${q.steps}${q.doing ? `: ${q.doing}` : ''}`;
  switch (q.state) {
    case 'stored': return `${q.steps} step${q.steps === 1 ? '' : 's'}${q.doing ? `, the first: ${q.doing}` : ''}`;
    case 'finished': return `went through its ${q.steps} step${q.steps === 1 ? '' : 's'}`;
    case 'aborted': return `stopped at ${at}`;
    default: return at;
  }
}

function sequenceEvent(e) {
  const f = e.in_force;
  return `<li data-what="${esc(e.what)}"><span class="when">${esc(new Date(e.at_unix_ns / 1e6).toLocaleTimeString())}</span> ${esc(e.what)}${e.step == null ? '' : ` (step ${esc(Number(e.step) + 1)})`}: ${esc(e.detail)}${f ? ` <span class="hint">→ ${esc(`revision ${f.revision}${f.task ? `, task ${f.task}` : ''}`)}</span>` : ''}</li>`;
}

// A sequence's card, part by part: each part is redrawn only when it changed (a button redrawn
// between an operator's press and release would lose the click, and `why` changes every poll
// while a step waits).
const SEQ_PARTS = ['head', 'step', 'why', 'buttons', 'history'];

function sequenceParts(q) {
  const history = (q.history || []).slice(-6).reverse().map(sequenceEvent).join('');
  return {
    head: `<b>${esc(q.name)}</b> <span class="state ${esc(q.state)}">${esc(q.state)}</span> <span class="hint">${esc(q.file)}</span>`,
    step: esc(sequenceStep(q)),
    why: esc(q.why || ''),
    buttons: (SEQ_ACTIONS[q.state] || []).map((a) => `<button data-seq-act="${a}" data-seq-name="${esc(q.name)}">${a[0].toUpperCase()}${a.slice(1)}</button>`).join(' '),
    history: history ? `<ol>${history}</ol>` : '',
  };
}

function setHtml(el, html) {
  if (el.dnmHtml === html) return;
  el.innerHTML = html;
  el.dnmHtml = html;
}

// The sequences the rover reports (as it last did when the link is down) and the station's last
// sequence commands with their fates.
function renderSequences() {
  const l = S.live && S.live.link;
  const rover = l && l.rover;
  const list = (rover && rover.sequences) || [];
  $('seq-note').textContent = !rover ? 'the rover has not answered yet'
    : !list.length ? 'no sequence stored on the rover'
      : !l.up ? 'as the rover last reported them (the link is down)' : '';
  const box = $('seq-list');
  const names = new Set(list.map((q) => q.name));
  for (const d of [...box.children]) if (!names.has(d.dataset.seq)) d.remove();
  list.forEach((q, i) => {
    let d = [...box.children].find((c) => c.dataset.seq === q.name);
    if (!d) {
      d = document.createElement('div');
      d.className = 'seq';
      d.dataset.seq = q.name;
      d.innerHTML = SEQ_PARTS.map((p) => `<div class="seq-${p}"></div>`).join('');
    }
    if (box.children[i] !== d) box.insertBefore(d, box.children[i] || null);
    d.dataset.state = q.state;
    const parts = sequenceParts(q);
    for (const p of SEQ_PARTS) setHtml(d.querySelector(`.seq-${p}`), parts[p]);
  });
  setHtml($('seq-commands'), S.outbox.filter((e) => e.order.cmd === 'sequence').slice(-5).reverse().map(outboxItem).join(''));
}

function onSequenceButton(ev) {
  const b = ev.target.closest && ev.target.closest('[data-seq-act]');
  if (!b) return;
  const act = b.dataset.seqAct, name = b.dataset.seqName;
  submit({ cmd: 'sequence', name, action: { do: act } }, `${act} sequence ${name}`);
}

// ---- polling ----------------------------------------------------------------------------------

async function pollLive() {
  try {
    S.live = await api('/api/live');
    noteFailures();
    $('system-name').textContent = `· ${S.live.system} (${S.live.station})`;
    const l = S.live.link;
    const ls = $('link-status');
    ls.className = l.up ? 'up' : 'down';
    ls.textContent = l.up ? `rover link up · ${l.rtt_ms == null ? '?' : l.rtt_ms.toFixed(0)} ms · loss ${(100 * l.loss).toFixed(0)} %` : `rover link DOWN${l.last_contact_ms == null ? '' : ` · last heard ${(l.last_contact_ms / 1000).toFixed(0)} s ago`}`;
    if (!S.draft) await loadNetlist(false);
    else if (!Object.keys(S.kinds).length) { await loadKinds(); fillPalette(); render(); }
    showDraftBase();
    renderSequences();
    if (S.view === 'connections') render(); else fillTaskSelect();
  } catch (e) {
    $('link-status').className = 'down';
    $('link-status').textContent = `station: ${e.message}`;
  }
  setTimeout(pollLive, 1000);
}

async function pollOutbox() {
  try {
    // The last commands, applies without their text: a page must not pull netlists each second.
    const got = await api('/commands?last=30&brief');
    const bySeq = new Map(S.outbox.map((e) => [e.seq, e]));
    for (const e of got) bySeq.set(e.seq, e);
    S.outbox = [...bySeq.values()].sort((a, b) => a.seq - b.seq).slice(-30);
    $('outbox').innerHTML = S.outbox.slice().reverse().map(outboxItem).join('');
    renderSequences();
  } catch (_) { /* the next poll tries again */ }
  setTimeout(pollOutbox, 1000);
}

// A channel's copy over time: a bar per stretch, what arrived live (green) under what was
// filled in from the rover's recording (blue), what is still missing (red).
function timelineSvg(t) {
  if (!t) return '';
  const n = t.live.length, w = 3, h = 16;
  const most = t.expected_per_bin || Math.max(1, ...t.live.map((l, i) => l + t.backfilled[i]));
  let bars = '';
  for (let i = 0; i < n; i++) {
    const live = Math.min(1, t.live[i] / most), back = Math.min(1 - live, t.backfilled[i] / most);
    const x = i * w;
    if (t.expected_per_bin && live + back < 0.9) bars += `<rect x="${x}" y="0" width="${w - 0.5}" height="${h}" class="tl-missing"/>`;
    bars += `<rect x="${x}" y="${h * (1 - live)}" width="${w - 0.5}" height="${h * live}" class="tl-live"/>`;
    bars += `<rect x="${x}" y="${h * (1 - live - back)}" width="${w - 0.5}" height="${h * back}" class="tl-back"/>`;
  }
  const span = ((t.to_ns - t.from_ns) / 1e9).toFixed(0);
  return `<svg class="timeline" width="${n * w}" height="${h}" viewBox="0 0 ${n * w} ${h}"><title>${span} s from the first message held: live (green), filled in from the rover's recording (blue), missing (red)</title>${bars}</svg>`;
}

// How complete the station's own record of the rover is (GET /downlink): a row per output.
function recordRow(c, now) {
  const pct = c.expected ? ` (${(100 * c.received / c.expected).toFixed(1)} %)` : '';
  const gap = c.oldest_gap
    ? `${((now - c.oldest_gap.from_ns) / 1e9).toFixed(0)} s ago, ${((c.oldest_gap.to_ns - c.oldest_gap.from_ns) / 1e9).toFixed(1)} s long${c.gaps > 1 ? ` (+${c.gaps - 1})` : ''}`
    : '–';
  const unrec = c.unrecorded.length
    ? c.unrecorded.map((g) => `${((g.to_ns - g.from_ns) / 1e9).toFixed(1)} s`).join(', ')
    : '–';
  const cls = c.gaps ? 'gappy' : 'whole';
  return `<tr class="${cls}" data-topic="${esc(c.topic)}"><td>${esc(c.topic)}</td><td>${esc(c.dnm || '')}</td>`
    + `<td>${c.rate_hz == null ? 'all' : `${c.rate_hz.toFixed(c.rate_hz < 1 ? 2 : 0)} Hz`}</td>`
    + `<td>${esc(c.received)} / ${esc(c.expected)}${pct}</td><td>${timelineSvg(c.timeline)}</td><td>${esc(gap)}</td>`
    + `<td>${(c.backlog_bytes / 1024).toFixed(1)} KiB</td><td>${esc(unrec)}</td></tr>`;
}

async function pollRecord() {
  try {
    const r = await api('/downlink');
    const kbit = (b) => (b * 8 / 1000).toFixed(1);
    const budget = r.budget_bytes_per_s == null ? 'no budget' : `budget ${kbit(r.budget_bytes_per_s)} kbit/s`;
    const clear = r.seconds_to_clear == null ? '' : ` · ~${r.seconds_to_clear.toFixed(0)} s to clear`;
    const paced = r.request_bytes ? ` · requests ≤ ${(r.request_bytes / 1024).toFixed(1)} KiB` : '';
    $('record-summary').textContent = `${r.dir} · ${budget}${paced} · downlink ${kbit(r.measured_bytes_per_s)} kbit/s · backlog ${(r.backlog_bytes / 1024).toFixed(1)} KiB${clear}`;
    const now = Date.now() * 1e6;
    // The plan's outputs first, then switches and events.
    const rows = r.channels.slice().sort((a, b) => (a.rate_hz == null) - (b.rate_hz == null) || a.topic.localeCompare(b.topic));
    $('record').querySelector('tbody').innerHTML = rows.map((c) => recordRow(c, now)).join('');
  } catch (_) { /* none kept, or the station is away: the next poll tries again */ }
  setTimeout(pollRecord, 2000);
}

// A command in words, as the outbox lists it.
function orderText(o) {
  switch (o.cmd) {
    case 'switch': return `switch to ${o.task}`;
    case 'apply': return `apply ${o.file}`;
    case 'module': return `${o.edit.op} ${o.edit.name}`;
    case 'cancel': return `cancel #${o.seq}`;
    case 'sequence': return `${o.action.do} sequence ${o.name}`;
    default: return o.cmd;
  }
}

// One command of the outbox: its state and what the rover said (a refusal's reason in full:
// a sequence's located errors take several lines).
function outboxItem(e) {
  const f = e.fate || {};
  const detail = f.reason ? ` — <span class="reason">${esc(f.reason)}</span>`
    : f.revision ? ` — ${esc(`revision ${f.revision}${f.task ? `, task ${f.task}` : ''}`)}`
      : f.detail ? ` — ${esc(f.detail)}` : '';
  return `<li data-seq="${esc(e.seq)}" data-state="${esc(e.state)}">#${esc(e.seq)} ${esc(orderText(e.order))} <span class="state ${esc(e.state)}">${esc(e.state)}</span>${detail}</li>`;
}

// Which revision the draft was taken from, and what applying it would do to the task in force.
function showDraftBase() {
  const el = $('draft-base');
  const w = S.live && S.live.live.wiring;
  if (!el || !S.base) return;
  const notes = [];
  if (w && w.revision !== S.base.revision) notes.push(`the rover is now at revision ${w.revision}: “From rover” takes it`);
  const active = w && w.active_task;
  if (active && S.draft && !tasks()[active]) notes.push(`the task in force (${active}) is not in the draft: applying it switches the rover to ${(S.draft.system && S.draft.system.default_task) || Object.keys(tasks())[0] || 'no task'}`);
  el.textContent = `draft of revision ${S.base.revision}${notes.length ? ' — ' + notes.join('; ') : ''}`;
  el.classList.toggle('warn', notes.length > 0);
}

async function loadKinds() {
  const list = await api('/api/kinds');
  S.kinds = Object.fromEntries(list.map((e) => [e.spec.name, e.spec]));
}

async function loadNetlist(force) {
  if (S.draft && !force) return;
  try {
    if (!Object.keys(S.kinds).length) await loadKinds();
    const n = await api('/api/netlist');
    S.base = n;
    S.draft = JSON.parse(JSON.stringify(n.doc));
    S.draftFile = (n.file || 'draft.toml').split('/').pop();
    S.task = n.active_task || Object.keys(tasks())[0] || null;
    S.selected = null;
    fillTaskSelect();
    fillPalette();
    say(`draft from the netlist in force (revision ${n.revision}, ${modules().length} modules)`, 'ok');
    scheduleCheck();
    render();
    if (!S.perf.firstDraftMs) S.perf.firstDraftMs = performance.now();
  } catch (e) {
    say(`no netlist yet: ${e.message}`, 'error');
  }
}

async function submit(order, what) {
  try {
    const e = await api('/commands', order);
    say(`${what}: command #${e.seq} ${e.state}; the outbox shows what the rover does with it`, 'ok');
  } catch (e) {
    say(`${what} refused: ${e.message}`, 'refused');
  }
}

function setView(v) {
  S.view = v;
  document.body.className = `view-${v}`;
  $('tab-tasks').classList.toggle('active', v === 'tasks');
  $('tab-connections').classList.toggle('active', v === 'connections');
  render();
}

// What the page costs the browser: tasks over 50 ms, and how long input events take to be
// answered (Event Timing), kept for whoever measures the page.
function observePerformance() {
  const keep = (list, v) => { list.push(v); if (list.length > 500) list.shift(); };
  try {
    new PerformanceObserver((l) => l.getEntries().forEach((e) => keep(S.perf.longTasks, e.duration)))
      .observe({ type: 'longtask', buffered: true });
  } catch (_) { /* not supported */ }
  try {
    new PerformanceObserver((l) => l.getEntries().forEach((e) => keep(S.perf.events, e.duration)))
      .observe({ type: 'event', durationThreshold: 16, buffered: true });
  } catch (_) { /* not supported */ }
}

function init() {
  observePerformance();
  document.body.className = 'view-tasks';
  $('tab-tasks').onclick = () => { location.hash = '#tasks'; };
  $('tab-connections').onclick = () => { location.hash = '#connections'; };
  $('task-select').onchange = (e) => { S.task = e.target.value; S.selected = null; render(); };
  $('task-new').onclick = () => taskAction('new');
  $('task-copy').onclick = () => taskAction('copy');
  $('task-rename').onclick = () => taskAction('rename');
  $('task-delete').onclick = () => taskAction('delete');
  $('draft-reset').onclick = () => loadNetlist(true);
  $('draft-apply').onclick = () => {
    if (!S.check || !S.check.ok) return;
    submit({ cmd: 'apply', file: S.check.file, text: S.check.toml }, 'apply');
  };
  $('task-switch').onclick = () => {
    // The rover decides: a task it does not have is refused there, with the reason, in the
    // outbox (the page's view of the netlist in force may be a second behind an apply).
    submit({ cmd: 'switch', task: S.task }, `switch to ${S.task}`);
  };
  $('draft-export').onclick = () => {
    if (!S.check) return;
    $('export-file').textContent = S.check.file + (S.check.ok ? '' : ' (not valid yet)');
    $('export-text').textContent = S.check.toml;
    const a = $('export-download');
    a.download = S.check.file;
    a.href = URL.createObjectURL(new Blob([S.check.toml], { type: 'application/toml' }));
    $('export-dialog').showModal();
  };
  $('export-close').onclick = () => $('export-dialog').close();
  $('task-step').onclick = addTaskStep;
  $('seq-file').onchange = loadSequenceFile;
  $('seq-upload').onclick = uploadSequence;
  $('sequences').addEventListener('click', onSequenceButton);
  const svg = $('canvas');
  svg.addEventListener('pointerdown', onPointerDown);
  window.addEventListener('pointermove', onPointerMove);
  window.addEventListener('pointerup', onPointerUp);
  window.addEventListener('keydown', (ev) => {
    if (ev.key !== 'Delete' || S.view !== 'tasks' || !S.selected || S.selected.type !== 'link') return;
    if (document.activeElement && /INPUT|SELECT/.test(document.activeElement.tagName)) return;
    const t = tasks()[S.task];
    if (!t || !t.links || !t.links[S.selected.index]) return;
    const [gone] = t.links.splice(S.selected.index, 1);
    S.selected = null;
    changed(`link ${gone} removed`);
  });
  window.addEventListener('hashchange', () => setView(location.hash === '#connections' ? 'connections' : 'tasks'));
  if (location.hash === '#connections') setView('connections');
  pollLive();
  pollOutbox();
  pollRecord();
}

init();
