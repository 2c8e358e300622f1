// Every API call goes through `api`, which adds the bearer token when one was given (kept in
// sessionStorage for this tab) and asks for one on 401.

import { $, TOKEN_KEY, state } from './util.js';
import { start } from './app.js';

class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

export function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (state.token) h.Authorization = 'Bearer ' + state.token;
  return h;
}

export async function describe(response) {
  try {
    const body = await response.json();
    const e = body.error || {};
    const details = (e.details || []).map((d) => (d.field ? d.field + ': ' : '') + d.message);
    return (e.message || response.statusText) + (details.length ? ' (' + details.join('; ') + ')' : '');
  } catch (_) {
    return response.status + ' ' + response.statusText;
  }
}

export async function api(path, options) {
  const opts = options || {};
  const init = { method: opts.method || 'GET', headers: headers(opts.headers), signal: opts.signal };
  if (opts.json !== undefined) {
    init.body = JSON.stringify(opts.json);
    init.headers['Content-Type'] = 'application/json';
  }
  const response = await fetch(path, init);
  if (response.status === 401) {
    askToken(await describe(response));
    throw new ApiError(401, 'a token is needed');
  }
  if (!response.ok) throw new ApiError(response.status, await describe(response));
  if (opts.raw) return response;
  return response.json();
}

// An HTML page of the API (a report), fetched with the token and shown in `tab` (opened by the
// caller on the click itself, so that no popup blocker holds it) from a blob; the blob takes
// this page's content policy, which admits the reports' style sheet by its hash. Throws as
// `api` does; says so when the browser opened no tab.
export async function openInTab(path, tab) {
  let response;
  try {
    response = await api(path, { raw: true });
  } catch (e) {
    if (tab) tab.close();
    throw e;
  }
  const url = URL.createObjectURL(new Blob([await response.text()], { type: 'text/html' }));
  if (!tab) {
    URL.revokeObjectURL(url);
    throw new ApiError(0, 'the browser opened no new tab (allow this page to open one)');
  }
  tab.location.href = url;
  setTimeout(() => URL.revokeObjectURL(url), 60000);
}

// token

let tokenAsked = false;
export function askToken(reason) {
  if (tokenAsked) return;
  tokenAsked = true;
  $('token-reason').textContent = reason
    ? 'The service answered: ' + reason + '. The token is kept for this browser tab only.'
    : 'The token is kept for this browser tab only.';
  $('token-input').value = '';
  if (!$('token-dialog').open) $('token-dialog').showModal();
}
$('token-button').addEventListener('click', () => {
  tokenAsked = false;
  askToken('');
});
$('token-dialog').addEventListener('close', () => {
  tokenAsked = false;
  const choice = $('token-dialog').returnValue;
  if (choice === 'save' && $('token-input').value.trim()) {
    state.token = $('token-input').value.trim();
    sessionStorage.setItem(TOKEN_KEY, state.token);
  } else if (choice === 'clear') {
    state.token = '';
    sessionStorage.removeItem(TOKEN_KEY);
  } else {
    return;
  }
  start();
});
