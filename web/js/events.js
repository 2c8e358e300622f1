// Live events from /api/v1/events, read with fetch (EventSource cannot send an Authorization
// header): results update the cards, alarms the alarm table.

import { $, clearMessage, showMessage, state } from './util.js';
import { askToken, describe, headers } from './api.js';
import { acceptCompensation, loadCompensation } from './cards.js';
import { acceptAcknowledgement, acceptAlarm } from './alarms.js';

let eventsAbort = null;
let eventsGeneration = 0;
function setLive(stateName, text) {
  $('live').dataset.state = stateName;
  $('live').textContent = text;
}

export async function runEvents() {
  if (eventsAbort) eventsAbort.abort();
  const generation = ++eventsGeneration;
  let delayMs = 1000;
  while (generation === eventsGeneration) {
    eventsAbort = new AbortController();
    try {
      const response = await fetch('/api/v1/events', {
        headers: headers({ Accept: 'text/event-stream' }),
        signal: eventsAbort.signal,
      });
      if (response.status === 401) {
        askToken(await describe(response));
        setLive('offline', 'needs a token');
        return;
      }
      if (!response.ok || !response.body) throw new Error(await describe(response));
      setLive('live', 'live');
      clearMessage('events');
      delayMs = 1000;
      // Results missed while disconnected: ask for the current ones once.
      for (const t of state.targets) loadCompensation(t.name).catch(() => {});
      await readEvents(response.body.getReader());
    } catch (e) {
      if (e.name === 'AbortError') return;
      showMessage('events', 'Live updates interrupted: ' + e.message + '. Reconnecting…');
    }
    if (generation !== eventsGeneration) return;
    setLive('reconnecting', 'reconnecting…');
    await new Promise((r) => setTimeout(r, delayMs));
    delayMs = Math.min(delayMs * 2, 15000);
  }
}

async function readEvents(reader) {
  const decoder = new TextDecoder();
  let buffer = '';
  let event = 'message';
  let data = [];
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += decoder.decode(value, { stream: true });
    let nl;
    while ((nl = buffer.indexOf('\n')) >= 0) {
      let line = buffer.slice(0, nl);
      buffer = buffer.slice(nl + 1);
      if (line.endsWith('\r')) line = line.slice(0, -1);
      if (line === '') {
        if (data.length) dispatch(event, data.join('\n'));
        event = 'message';
        data = [];
      } else if (line.startsWith(':')) {
        // keep-alive comment
      } else {
        const colon = line.indexOf(':');
        const field = colon < 0 ? line : line.slice(0, colon);
        let v = colon < 0 ? '' : line.slice(colon + 1);
        if (v.startsWith(' ')) v = v.slice(1);
        if (field === 'event') event = v;
        else if (field === 'data') data.push(v);
      }
    }
  }
}

function dispatch(event, text) {
  let body;
  try {
    body = JSON.parse(text);
  } catch (_) {
    return;
  }
  if (event === 'result') acceptCompensation(body);
  else if (event === 'alarm') acceptAlarm(body);
  else if (event === 'acknowledgement') acceptAcknowledgement(body);
}
