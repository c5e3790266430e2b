// fleetmem dashboard: reads the REST API of the server that serves it
// (/v1/fleets, /stats, /clusters?includePlaces=true, /events?after=N) and
// redraws without reloading. No framework, no build step, nothing fetched
// from elsewhere.
'use strict';

const state = {
  token: sessionStorage.getItem('fleetmem-token') || '',
  fleets: [],
  aliases: [],           // [{alias, fleetId}] (ListAliases)
  fleet: null,           // selected fleet id
  stats: null,
  clusters: null,
  events: [],            // newest last, at most MAX_EVENTS
  lastEventId: 0,
  fading: [],            // forgotten clusters: {x, y, r, at}
  history: [],           // [{t, traces, clusters, forgotten}] from events
  colourBy: 'robot',
};
const MAX_EVENTS = 500;
const FADE_MS = 12000;
const LANE_PX = 4;
const PALETTE = ['#2b6cb0', '#dd6b20', '#2f855a', '#805ad5', '#d53f8c', '#319795',
  '#b7791f', '#4a5568', '#e53e3e', '#38a169', '#3182ce', '#975a16'];

// The address's #fragment: fleet=ID (each fleet has its own link),
// unit=NAME (what a place's x, y are: "m" for a metric map, "route index"
// for Nordland; "units" if not said) and token=NAME:SECRET (for scripts;
// taken once, then removed from the address).
function hashParams() {
  return new URLSearchParams(location.hash.replace(/^#/, ''));
}
(function tokenFromHash() {
  const params = hashParams();
  if (params.has('token')) {
    state.token = params.get('token');
    sessionStorage.setItem('fleetmem-token', state.token);
    params.delete('token');
    const rest = params.toString();
    history.replaceState(null, '', location.pathname + (rest ? '#' + rest : ''));
  }
})();
const placeUnit = () => hashParams().get('unit') || 'units';

function fleetLink(fleetId) {
  const params = hashParams();
  params.set('fleet', fleetId);
  return '#' + params.toString();
}

window.addEventListener('hashchange', () => {
  const wanted = hashParams().get('fleet');
  if (wanted && wanted !== state.fleet) selectFleet(wanted);
  drawMap();
});

class AuthError extends Error {}

async function api(path, body) {
  const headers = state.token ? { Authorization: 'Bearer ' + state.token } : {};
  const init = { headers, cache: 'no-store' };
  if (body !== undefined) {  // a POST of a JSON body (the fleet's deletion)
    init.method = 'POST';
    init.body = JSON.stringify(body);
    headers['Content-Type'] = 'application/json';
  }
  const response = await fetch(path, init);
  if (response.status === 401) throw new AuthError('credentials needed');
  const answer = await response.json();
  if (!response.ok) throw new Error(answer.message || response.statusText);
  return answer;
}

const num = (v) => Number(v || 0);
const fmt = (v) => num(v).toLocaleString('en-US');
const plural = (n, word) => `${fmt(n)} ${word}${num(n) === 1 ? '' : 's'}`;
const PICKER_ROWS = 50;  // fleets listed at once; the search narrows them
const $ = (id) => document.getElementById(id);

function colourOf(key) {
  let h = 0;
  for (const c of key) h = (h * 31 + c.charCodeAt(0)) >>> 0;
  return PALETTE[h % PALETTE.length];
}

function setStatus(text, error) {
  $('status').textContent = text;
  $('status').className = error ? 'error' : 'muted';
}

function showLogin(message) {
  $('login').hidden = false;
  $('main').hidden = true;
  $('login-error').textContent = message || '';
  setStatus('credentials needed');
}

$('login-form').addEventListener('submit', (event) => {
  event.preventDefault();
  state.token = $('login-token').value.trim();
  sessionStorage.setItem('fleetmem-token', state.token);
  $('login').hidden = true;
  refreshFleets();
});

// The fleet's deletion: enabled only once its id is typed in full.
$('delete-name').addEventListener('input', (event) => {
  $('delete-button').disabled = event.target.value !== state.fleet;
});
$('delete-button').addEventListener('click', async () => {
  const fleet = state.fleet;
  if (!fleet || $('delete-name').value !== fleet) return;
  $('delete-button').disabled = true;
  try {
    const answer = await api(`/v1/fleets/${encodeURIComponent(fleet)}/delete`, {});
    $('delete-result').textContent = `fleet ${fleet} deleted (${fmt(answer.tracesDeleted)} traces)`;
    $('delete-name').value = '';
    state.fleet = null;
    await refreshFleets();
  } catch (error) {
    $('delete-result').textContent = `not deleted: ${error.message}`;
  }
});

$('colour-by').addEventListener('change', (event) => {
  state.colourBy = event.target.value;
  drawMap();
});

function selectFleet(fleetId) {
  if (state.fleet === fleetId) return;
  state.fleet = fleetId;
  if (hashParams().get('fleet') !== fleetId) {
    history.replaceState(null, '', location.pathname + fleetLink(fleetId));
  }
  state.stats = null;
  state.clusters = null;
  state.events = [];
  state.lastEventId = 0;
  state.fading = [];
  state.history = [];
  $('events').innerHTML = '';
  $('delete-name').value = '';
  $('delete-button').disabled = true;
  renderFleetList();
  refreshFleet();
  refreshMap();
}

// The fleet picker: a button naming the fleet shown; it opens a list of
// the fleets that match the search (id or alias), the selected one first,
// at most PICKER_ROWS of them, so that it works with hundreds of fleets.
function openPicker(open) {
  $('fleet-popup').hidden = !open;
  $('fleet-current').setAttribute('aria-expanded', String(open));
  if (open) {
    $('fleet-search').focus();
    renderFleetList();
  }
}
$('fleet-current').addEventListener('click', () => openPicker($('fleet-popup').hidden));
$('fleet-search').addEventListener('input', renderFleetList);
$('fleet-search').addEventListener('keydown', (event) => {
  if (event.key === 'Escape') openPicker(false);
  if (event.key === 'Enter') {  // the first match
    const first = $('fleet-list').querySelector('a');
    if (first) location.hash = first.getAttribute('href');
    openPicker(false);
  }
});
document.addEventListener('click', (event) => {
  if (!$('picker').contains(event.target)) openPicker(false);
});

function renderFleetList() {
  const query = $('fleet-search').value.trim().toLowerCase();
  const aliasesOf = (id) => state.aliases.filter((a) => a.fleetId === id).map((a) => a.alias);
  const matches = state.fleets.filter((fleet) => !query ||
    fleet.fleetId.toLowerCase().includes(query) ||
    aliasesOf(fleet.fleetId).some((alias) => alias.toLowerCase().includes(query)));
  matches.sort((a, b) => (b.fleetId === state.fleet) - (a.fleetId === state.fleet) ||
    a.fleetId.localeCompare(b.fleetId));
  const nav = $('fleet-list');
  nav.innerHTML = '';
  for (const fleet of matches.slice(0, PICKER_ROWS)) {
    const link = document.createElement('a');
    link.href = fleetLink(fleet.fleetId);
    link.dataset.fleet = fleet.fleetId;
    const names = aliasesOf(fleet.fleetId);
    const name = document.createElement('span');
    name.textContent = fleet.fleetId + (names.length ? ` ← ${names.join(', ')}` : '');
    const counts = document.createElement('span');
    counts.className = 'muted';
    counts.textContent = `${plural(fleet.traces, 'trace')} · ${plural(fleet.robots, 'robot')}`;
    link.append(name, counts);
    if (names.length) link.dataset.aliases = names.join(',');
    if (fleet.fleetId === state.fleet) link.className = 'active';
    // A plain link: the hashchange selects it (and it opens in a new tab).
    link.addEventListener('click', () => openPicker(false));
    nav.appendChild(link);
  }
  const left = matches.length - Math.min(matches.length, PICKER_ROWS);
  $('fleet-more').textContent = (left > 0 ? `${fmt(left)} more: type to narrow. ` : '') +
    `${plural(state.fleets.length, 'fleet')} on this server` +
    (query ? `, ${fmt(matches.length)} matching` : '');
  $('fleet-search').placeholder = `search ${plural(state.fleets.length, 'fleet')} and aliases`;
  const current = state.fleets.find((f) => f.fleetId === state.fleet);
  $('fleet-current').textContent = current ? current.fleetId : 'choose a fleet';
  $('fleet-current').title = current
    ? `${plural(current.traces, 'trace')} · ${plural(current.robots, 'robot')}` : '';
}

async function refreshFleets() {
  try {
    const answer = await api('/v1/fleets');
    state.fleets = answer.fleets || [];
    // The names that stand for fleets (an older server has none).
    state.aliases = await api('/v1/aliases').then((a) => a.aliases || [], () => []);
    $('login').hidden = true;
    $('empty').hidden = state.fleets.length > 0;
    $('main').hidden = state.fleets.length === 0;
    // #fleet= may name an alias: the fleet it names now.
    const named = hashParams().get('fleet');
    const alias = state.aliases.find((a) => a.alias === named);
    const wanted = alias ? alias.fleetId : named;
    if (!state.fleet && state.fleets.length > 0) {
      selectFleet(state.fleets.some((f) => f.fleetId === wanted) ? wanted : state.fleets[0].fleetId);
    }
    renderFleetList();
    setStatus('live · ' + new Date().toLocaleTimeString());
  } catch (error) {
    if (error instanceof AuthError) {
      showLogin(state.token ? 'That token was not accepted.' : '');
    } else {
      setStatus('server unreachable: ' + error.message, true);
    }
  }
}

async function refreshFleet() {
  if (!state.fleet) return;
  const fleet = state.fleet;
  try {
    const stats = await api(`/v1/fleets/${encodeURIComponent(fleet)}/stats`);
    if (fleet !== state.fleet) return;
    state.stats = stats;
    renderStats();
    // The fleet's settings (GetFleet), a line under the counts.
    const info = await api(`/v1/fleets/${encodeURIComponent(fleet)}`);
    if (fleet !== state.fleet) return;
    renderSettings(info.fleet || {});
    await readEvents(fleet);
  } catch (error) {
    if (error instanceof AuthError) showLogin(); else setStatus(error.message, true);
  }
}

async function readEvents(fleet) {
  // Pages of up to 1,000 events until caught up.
  for (let page = 0; page < 20; ++page) {
    const answer = await api(`/v1/fleets/${encodeURIComponent(fleet)}/events?after=${state.lastEventId}`);
    if (fleet !== state.fleet) return;
    const events = answer.events || [];
    if (events.length === 0) break;
    const live = state.lastEventId > 0;
    for (const event of events) addEvent(event, live);
    state.lastEventId = num(answer.lastEventId);
  }
  drawChart();
}

function addEvent(event, live) {
  const merged = event.type === 'CLUSTER_MERGED';
  // Traces deleted from a cluster (cluster 0: from the pending ones, which
  // the chart does not count); a cluster left empty leaves.
  const deleted = event.type === 'TRACES_DELETED';
  const clusterLeft = deleted && num(event.clusterId) > 0 &&
    num(event.traceCount) === 0;
  // A cluster leaves the memory: forgotten whole, or merged into another.
  const forgotten = event.type === 'CLUSTER_FORGOTTEN' || merged;
  state.events.push(event);
  if (state.events.length > MAX_EVENTS) state.events.shift();
  const last = state.history.length ? state.history[state.history.length - 1]
    : { traces: 0, clusters: 0, forgotten: 0 };
  // A merge removes only what it dropped; its traces live on in merged_into.
  let traceChange = merged ? -num(event.tracesDropped)
    : (forgotten ? -1 : 1) * num(event.traceCount);
  let clusterChange = forgotten ? -1 : 1;
  if (deleted) {
    traceChange = num(event.clusterId) > 0 ? -num(event.tracesDropped) : 0;
    clusterChange = clusterLeft ? -1 : 0;
  }
  // One point per change of state: a consolidation's events (clusters
  // added, then forgotten or merged) share its timestamp and make one step,
  // so the chart never shows the half-applied memory between them (which
  // rose above K_max).
  const point = {
    t: num(event.timestampNs) / 1e6,
    traces: last.traces + traceChange,
    clusters: last.clusters + clusterChange,
    forgotten: last.forgotten + (forgotten ? 1 : 0),
  };
  if (state.history.length && last.t === point.t) {
    state.history[state.history.length - 1] = point;
  } else {
    state.history.push(point);
  }
  if (forgotten && live && event.centroidPose) {
    state.fading.push({ x: event.centroidPose.x, y: event.centroidPose.y,
      n: num(event.traceCount), at: performance.now() });
  }
  const item = document.createElement('li');
  item.value = num(event.id);
  item.className = (forgotten || deleted ? 'forgotten' : 'added') +
    (live ? ' fresh' : '');
  const when = new Date(num(event.timestampNs) / 1e6).toLocaleTimeString();
  const pose = event.centroidPose || {};
  let verb = merged ? `merged cluster ${event.clusterId} into ${event.mergedInto}`
    : `${forgotten ? 'forgot' : 'added'} cluster ${event.clusterId}`;
  if (deleted) {
    verb = `deleted ${num(event.tracesDropped)} traces of ` +
      (num(event.clusterId) > 0 ? `cluster ${event.clusterId}` : 'the pending');
  }
  item.textContent = `${when} ${verb}` +
    ` · ${num(event.traceCount)} traces` + (clusterLeft ? ' (removed)' : '') +
    (merged ? ` (${num(event.tracesDropped)} dropped)` : '') +
    ` · robot ${event.robotId}` +
    (event.domain ? ` · ${event.domain}` : '') +
    ` · at (${num(pose.x).toFixed(0)}, ${num(pose.y).toFixed(0)})`;
  const list = $('events');
  list.insertBefore(item, list.firstChild);
  while (list.children.length > 200) list.removeChild(list.lastChild);
  if (live) setTimeout(() => item.classList.remove('fresh'), 3000);
  $('events-live').textContent = `last event #${event.id}`;
}

function renderSettings(fleet) {
  const s = fleet.settings || {};
  const retention = [];
  if (num(s.maxAgeSeconds) > 0) retention.push(`max age ${fmt(s.maxAgeSeconds)} s`);
  if (num(s.maxTracesPerRobot) > 0) retention.push(`${fmt(s.maxTracesPerRobot)} traces per robot`);
  $('fleet-settings').textContent =
    `settings (${fleet.ownSettings ? "the fleet's own" : "the server's"}): ` +
    `${fmt(s.codeDimension)}-d codes` + (s.encoderVersion ? ` of ${s.encoderVersion}` : '') +
    (s.placeUnit ? `, places in ${s.placeUnit}` : '') +
    ` · K ${fmt(s.clustersPerSegment)} · N_max ${fmt(s.maxTracesPerCluster)}` +
    ` · K_max ${fmt(s.maxClusters)} · γ ${s.replayDecay}` +
    ` · forgetting ${s.forgetting === 'FORGETTING_RULE_DROP' ? 'drops' : 'merges'}` +
    ` · refresh ${s.refreshUniform ? 'uniform' : 'by γⁿR'}` +
    (num(s.refreshPairRadius) > 0 ? `, in pairs within ${s.refreshPairRadius}` : '') +
    ` · retention: ${retention.length ? retention.join(', ') : 'none'}`;
}

function renderStats() {
  const s = state.stats;
  $('stat-traces').textContent = fmt(s.traces);
  $('stat-pending').textContent = fmt(s.pendingTraces);
  $('stat-clusters').textContent = fmt(s.clusters);
  $('stat-bound').textContent = s.maxClusters ? ` / ${fmt(s.maxClusters)}` : '';
  $('stat-robots').textContent = fmt((s.robots || []).length);
  $('stat-consolidations').textContent = fmt(s.consolidations);
  $('stat-forgotten').textContent = fmt(s.clustersForgotten);
  const total = Math.max(1, num(s.traces));
  const robots = $('robots').tBodies[0];
  robots.innerHTML = '';
  for (const r of s.robots || []) {
    const row = robots.insertRow();
    row.dataset.robot = r.robotId;
    const share = num(r.traces) / total;
    const name = row.insertCell();
    name.innerHTML = `<i class="dot" style="display:inline-block;width:.7em;height:.7em;border-radius:50%;margin-right:.3em;background:${colourOf(r.robotId)}"></i>`;
    name.appendChild(document.createTextNode(r.robotId));
    for (const v of [r.traces, r.pendingTraces, r.received, r.replayed]) {
      row.insertCell().textContent = fmt(v);
    }
    row.insertCell().innerHTML =
      `<span class="bar" style="width:${Math.round(share * 80)}px"></span>${(share * 100).toFixed(0)}%`;
  }
  const domains = $('domains').tBodies[0];
  domains.innerHTML = '';
  for (const d of s.domains || []) {
    const row = domains.insertRow();
    row.dataset.domain = d.domain;
    row.insertCell().textContent = d.domain || '(none)';
    row.insertCell().textContent = fmt(d.traces);
    row.insertCell().textContent = fmt(d.pendingTraces);
  }
}

async function refreshMap() {
  if (!state.fleet) return;
  const fleet = state.fleet;
  try {
    const answer = await api(`/v1/fleets/${encodeURIComponent(fleet)}/clusters?includePlaces=true`);
    if (fleet !== state.fleet) return;
    state.clusters = answer;
    drawMap();
  } catch (error) {
    if (error instanceof AuthError) showLogin(); else setStatus(error.message, true);
  }
}

function drawMap() {
  const canvas = $('map');
  const ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const data = state.clusters;
  if (!data) return;
  const clusters = data.clusters || [];
  const pending = data.pending || [];
  const points = [];
  for (const c of clusters) for (const p of c.places || []) points.push(p);
  const all = points.concat(pending);
  const extent = { x0: Infinity, x1: -Infinity, y0: Infinity, y1: -Infinity };
  for (const p of all) {
    const pose = p.pose || {};
    extent.x0 = Math.min(extent.x0, num(pose.x)); extent.x1 = Math.max(extent.x1, num(pose.x));
    extent.y0 = Math.min(extent.y0, num(pose.y)); extent.y1 = Math.max(extent.y1, num(pose.y));
  }
  for (const f of state.fading) {
    extent.x0 = Math.min(extent.x0, f.x); extent.x1 = Math.max(extent.x1, f.x);
    extent.y0 = Math.min(extent.y0, f.y); extent.y1 = Math.max(extent.y1, f.y);
  }
  if (!isFinite(extent.x0)) { extent.x0 = 0; extent.x1 = 1; extent.y0 = 0; extent.y1 = 1; }
  const pad = 30;
  const spanX = Math.max(1e-6, extent.x1 - extent.x0);
  const spanY = Math.max(1e-6, extent.y1 - extent.y0);
  const keyOf = (p) => (state.colourBy === 'robot' ? p.robotId : (p.domain || '(none)'));
  // Robots that pass the same places (the same route, a shared corridor)
  // would hide each other: each robot's dots are drawn in its own lane,
  // LANE_PX apart across the map, when colouring by robot.
  const robots = [...new Set(all.map((p) => p.robotId))].sort();
  const lane = (p) => (state.colourBy === 'robot'
    ? (robots.indexOf(p.robotId) - (robots.length - 1) / 2) * LANE_PX : 0);
  // Places on one line (every y within 1 % of the x span: a route index,
  // as Nordland's) would be one thin line across an empty map: the line is
  // folded into rows that fill the map instead, each labelled with the
  // place it starts at.
  const oneD = extent.y1 - extent.y0 <= 0.01 * spanX && all.length > 1;
  const rowHeight = Math.max(28, robots.length * LANE_PX + 20);
  const rows = oneD ? Math.max(1, Math.floor((canvas.height - 2 * pad) / rowHeight)) : 1;
  const rowSpan = spanX / rows;
  const scale = oneD ? (canvas.width - 2 * pad - 40) / rowSpan
    : Math.min((canvas.width - 2 * pad) / spanX, (canvas.height - 2 * pad) / spanY);
  const rowOf = (x) => Math.min(rows - 1, Math.max(0, Math.floor((x - extent.x0) / rowSpan)));
  // Canvas coordinates of a place (x, y).
  const sx = oneD ? (x) => pad + 40 + (x - extent.x0 - rowOf(x) * rowSpan) * scale
    : (x) => pad + (x - extent.x0) * scale + ((canvas.width - 2 * pad) - spanX * scale) / 2;
  const sy = oneD ? (x) => pad + rowOf(x) * rowHeight + rowHeight / 2
    : (x, y) => canvas.height - pad - (y - extent.y0) * scale - ((canvas.height - 2 * pad) - spanY * scale) / 2;
  canvas.dataset.layout = oneD ? `1-d, ${rows} rows` : '2-d';
  if (oneD) {
    ctx.strokeStyle = '#e2e8f0'; ctx.fillStyle = '#718096'; ctx.lineWidth = 1;
    ctx.font = '11px system-ui'; ctx.textAlign = 'right';
    for (let row = 0; row < rows; ++row) {
      const y = pad + row * rowHeight + rowHeight / 2;
      ctx.beginPath(); ctx.moveTo(pad + 40, y); ctx.lineTo(canvas.width - pad, y); ctx.stroke();
      ctx.fillText(fmt(Math.round(extent.x0 + row * rowSpan)), pad + 34, y + 4);
    }
    ctx.textAlign = 'left';
  }

  // Scale bar: a round number of the fleet's place unit.
  const length = Math.pow(10, Math.floor(Math.log10((oneD ? rowSpan : spanX) / 4 || 1)));
  ctx.strokeStyle = '#4a5568'; ctx.fillStyle = '#4a5568'; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(pad, canvas.height - 10); ctx.lineTo(pad + length * scale, canvas.height - 10); ctx.stroke();
  ctx.font = '12px system-ui';
  ctx.fillText(`${fmt(length)} ${placeUnit()}`, pad + length * scale + 6, canvas.height - 6);
  canvas.dataset.unit = placeUnit();

  const keys = new Map();
  for (const p of points) {
    const colour = colourOf(keyOf(p));
    keys.set(keyOf(p), colour);
    ctx.fillStyle = colour;
    ctx.globalAlpha = 0.75;
    ctx.beginPath(); ctx.arc(sx(num(p.pose.x)), sy(num(p.pose.x), num(p.pose.y)) + lane(p), 2.5, 0, 2 * Math.PI); ctx.fill();
  }
  ctx.globalAlpha = 1;
  for (const p of pending) {
    const colour = colourOf(keyOf(p));
    keys.set(keyOf(p), colour);
    ctx.strokeStyle = colour; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.arc(sx(num(p.pose.x)), sy(num(p.pose.x), num(p.pose.y)) + lane(p), 2.5, 0, 2 * Math.PI); ctx.stroke();
  }
  for (const c of clusters) {
    const pose = c.centroidPose || {};
    ctx.strokeStyle = '#1a202c'; ctx.lineWidth = 1.2; ctx.globalAlpha = 0.6;
    ctx.beginPath(); ctx.arc(sx(num(pose.x)), sy(num(pose.x), num(pose.y)), 3 + 2 * Math.sqrt(num(c.traceCount)), 0, 2 * Math.PI); ctx.stroke();
  }
  const now = performance.now();
  state.fading = state.fading.filter((f) => now - f.at < FADE_MS);
  for (const f of state.fading) {
    ctx.globalAlpha = 1 - (now - f.at) / FADE_MS;
    ctx.strokeStyle = '#c53030'; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(sx(f.x), sy(f.x, f.y), 3 + 2 * Math.sqrt(f.n), 0, 2 * Math.PI); ctx.stroke();
  }
  ctx.globalAlpha = 1;
  canvas.dataset.points = String(points.length + pending.length);
  canvas.dataset.clusters = String(clusters.length);
  const legend = $('legend');
  legend.innerHTML = '';
  for (const [key, colour] of [...keys.entries()].sort()) {
    const span = document.createElement('span');
    span.innerHTML = `<i style="background:${colour}"></i>`;
    span.appendChild(document.createTextNode(key));
    legend.appendChild(span);
  }
}

function drawChart() {
  const canvas = $('chart');
  const ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const h = state.history;
  if (h.length === 0) return;
  const pad = { l: 50, r: 50, t: 10, b: 24 };
  const t0 = h[0].t;
  const t1 = Math.max(h[h.length - 1].t, Date.now());
  const maxTraces = Math.max(1, ...h.map((p) => p.traces));
  const maxCount = Math.max(1, ...h.map((p) => Math.max(p.clusters, p.forgotten)));
  const x = (t) => pad.l + (t - t0) / Math.max(1, t1 - t0) * (canvas.width - pad.l - pad.r);
  const yl = (v) => canvas.height - pad.b - v / maxTraces * (canvas.height - pad.t - pad.b);
  const yr = (v) => canvas.height - pad.b - v / maxCount * (canvas.height - pad.t - pad.b);
  const line = (colour, y, key) => {
    ctx.strokeStyle = colour; ctx.lineWidth = 2; ctx.beginPath();
    h.forEach((p, i) => {
      // Steps: the value holds until the next event.
      if (i === 0) ctx.moveTo(x(p.t), y(p[key]));
      else { ctx.lineTo(x(p.t), y(h[i - 1][key])); ctx.lineTo(x(p.t), y(p[key])); }
    });
    ctx.lineTo(x(t1), y(h[h.length - 1][key]));
    ctx.stroke();
  };
  ctx.strokeStyle = '#e2e8f0'; ctx.lineWidth = 1;
  ctx.strokeRect(pad.l, pad.t, canvas.width - pad.l - pad.r, canvas.height - pad.t - pad.b);
  // Ticks: quarters of both value axes, five times along the bottom.
  ctx.fillStyle = '#4a5568'; ctx.font = '11px system-ui';
  let ticks = 0;
  for (let i = 0; i <= 4; ++i) {
    const yPixel = canvas.height - pad.b - i / 4 * (canvas.height - pad.t - pad.b);
    ctx.beginPath(); ctx.moveTo(pad.l - 4, yPixel); ctx.lineTo(canvas.width - pad.r + 4, yPixel); ctx.stroke();
    if (i > 0 && i < 4) {
      ctx.textAlign = 'right'; ctx.fillText(fmt(Math.round(maxTraces * i / 4)), pad.l - 6, yPixel + 4);
      ctx.textAlign = 'left'; ctx.fillText(fmt(Math.round(maxCount * i / 4)), canvas.width - pad.r + 6, yPixel + 4);
    }
    const t = t0 + (t1 - t0) * i / 4;
    ctx.beginPath(); ctx.moveTo(x(t), canvas.height - pad.b); ctx.lineTo(x(t), canvas.height - pad.b + 4); ctx.stroke();
    ctx.textAlign = i === 0 ? 'left' : (i === 4 ? 'right' : 'center');
    ctx.fillText(new Date(t).toLocaleTimeString(), x(t), canvas.height - 6);
    ticks += 3;
  }
  ctx.textAlign = 'left';
  canvas.dataset.ticks = String(ticks);
  canvas.dataset.peakClusters = String(Math.max(...h.map((p) => p.clusters)));
  line('#2b6cb0', yl, 'traces');
  line('#2f855a', yr, 'clusters');
  line('#c53030', yr, 'forgotten');
  ctx.fillStyle = '#4a5568'; ctx.font = '11px system-ui';
  ctx.fillText(fmt(maxTraces), 4, pad.t + 10);
  ctx.fillText('traces', 4, pad.t + 24);
  ctx.fillText(fmt(maxCount), canvas.width - pad.r + 4, pad.t + 10);
  ctx.fillText('clusters', canvas.width - pad.r + 4, pad.t + 24);
}

refreshFleets();
setInterval(refreshFleets, 5000);
setInterval(refreshFleet, 1000);
setInterval(refreshMap, 4000);
setInterval(() => { if (state.fading.length) drawMap(); }, 200);
