// The dashboard's entry point: hash routes (#/, #/vehicle/ID, #/profiles), one live stream per view,
// the API token form and the connection indicator.

import { AlarmStore } from './alarms.js';
import { authHeaders, getToken, setToken } from './api.js';
import { FleetView } from './fleet.js';
import { ProfilesView } from './profiles.js';
import { EventStream } from './stream.js';
import { VehicleView } from './vehicle.js';

const CONNECTION_TEXT = {
  connecting: 'connecting…',
  live: 'live',
  reconnecting: 'reconnecting…',
  unauthorized: 'token needed to read',
  notfound: 'not found',
  error: 'service error',
};

const alarms = new AlarmStore();
const tokenInput = document.getElementById('token-input');
const tokenState = document.getElementById('token-state');
const connection = document.getElementById('connection');
const badge = document.getElementById('alarm-badge');

function askForToken() {
  tokenState.textContent = 'enter the token';
  tokenInput.focus();
}

const views = {
  fleet: new FleetView(alarms, askForToken),
  vehicle: new VehicleView(alarms, askForToken),
  profiles: new ProfilesView(askForToken),
};

let stream = null;
let current = null;
let hello = null;

function route() {
  const hash = decodeURIComponent(location.hash.replace(/^#\/?/, ''));
  if (hash.startsWith('vehicle/')) return { view: 'vehicle', vehicle: hash.slice('vehicle/'.length) };
  if (hash === 'profiles') return { view: 'profiles', vehicle: null };
  return { view: 'fleet', vehicle: null };
}

function showConnection(state, detail) {
  connection.dataset.state = state;
  connection.textContent = CONNECTION_TEXT[state] || state;
  connection.title = detail || '';
  if (current && current.view === 'vehicle') {
    if (state === 'notfound') views.vehicle.notFound(detail || 'No such vehicle');
    if (state === 'live') views.vehicle.found();
  }
  if (state === 'unauthorized') askForToken();
}

function onEvent(name, data) {
  const view = current ? current.view : null;
  if (name === 'hello') {
    hello = data;
    if (view === 'vehicle') views.vehicle.onHello(data);
  } else if (name === 'alarms') {
    alarms.apply(data);
  } else if (name === 'fleet' && view === 'fleet' && hello) {
    views.fleet.apply(data, hello.fleet_columns);
  } else if (name === 'ownership' && view === 'fleet') {
    views.fleet.onOwnership(data, hello ? hello.replica : '');
  } else if (name === 'status' && view === 'vehicle') {
    views.vehicle.onStatus(data);
  } else if (name === 'trace' && view === 'vehicle') {
    views.vehicle.onTrace(data);
  }
}

function updateBadge() {
  const open = [...alarms.alarms.values()].filter((a) => !a.acknowledged).length;
  badge.hidden = open === 0;
  badge.textContent = `${open} unacknowledged alarm${open === 1 ? '' : 's'}`;
}
alarms.subscribe(updateBadge);

function open() {
  const next = route();
  if (current && current.view === next.view && current.vehicle === next.vehicle) return;
  if (stream) stream.stop();
  if (current) {
    views[current.view].leave?.();
    document.getElementById(`view-${current.view}`).hidden = true;
  }
  current = next;
  hello = null;
  document.getElementById(`view-${next.view}`).hidden = false;
  for (const link of document.querySelectorAll('[data-nav]')) {
    if (link.dataset.nav === next.view) link.setAttribute('aria-current', 'page');
    else link.removeAttribute('aria-current');
  }
  document.title = {
    fleet: 'Fleet · AGV fault estimator',
    vehicle: `${next.vehicle} · AGV fault estimator`,
    profiles: 'Profiles · AGV fault estimator',
  }[next.view];
  if (next.view === 'fleet') views.fleet.clear();
  if (next.view === 'vehicle') views.vehicle.enter(next.vehicle);
  if (next.view === 'profiles') views.profiles.enter();
  const query = new URLSearchParams({ view: next.view });
  if (next.vehicle) query.set('vehicle', next.vehicle);
  stream = new EventStream(`/ui/stream?${query}`, { headers: authHeaders, onEvent, onState: showConnection }).start();
  document.getElementById('main').focus({ preventScroll: true });
}

document.getElementById('token-form').addEventListener('submit', (event) => {
  event.preventDefault();
  setToken(tokenInput.value.trim());
  tokenState.textContent = tokenInput.value.trim() ? 'saved' : 'cleared';
  if (connection.dataset.state === 'unauthorized') {
    current = null; // reconnect with the token
    open();
  }
});
tokenInput.value = getToken();
tokenState.textContent = getToken() ? 'saved' : '';

window.addEventListener('hashchange', open);
open();
