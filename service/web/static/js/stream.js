// One server-sent-event stream read with fetch (so the API token can travel in a header, never in a URL),
// reconnecting with exponential back-off. Events are "event: NAME\ndata: JSON\n\n" blocks.

const MIN_DELAY_MS = 500;
const MAX_DELAY_MS = 10000;
const NOT_FOUND_DELAY_MS = 5000;

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

export class EventStream {
  /**
   * @param {string} url
   * @param {{headers: () => Record<string,string>, onEvent: (name: string, data: any) => void,
   *          onState: (state: string, detail?: string) => void}} handlers
   */
  constructor(url, { headers, onEvent, onState }) {
    this.url = url;
    this.headers = headers;
    this.onEvent = onEvent;
    this.lastState = null;
    this.onState = (state, detail) => {
      this.lastState = state;
      onState(state, detail);
    };
    this.stopped = false;
    this.abort = new AbortController();
  }

  start() {
    this.loop();
    return this;
  }

  stop() {
    this.stopped = true;
    this.abort.abort();
  }

  async loop() {
    let delay = MIN_DELAY_MS;
    while (!this.stopped) {
      this.onState('connecting');
      try {
        const response = await fetch(this.url, {
          headers: { Accept: 'text/event-stream', ...this.headers() },
          signal: this.abort.signal,
          cache: 'no-store',
        });
        if (response.status === 401) {
          this.onState('unauthorized', 'the API token is missing or refused');
        } else if (response.status === 404) {
          // a vehicle not seen yet: ask again now and then, it may start sending
          const body = await response.json().catch(() => ({}));
          this.onState('notfound', body.detail || 'not found');
          delay = Math.max(delay, NOT_FOUND_DELAY_MS);
        } else if (!response.ok) {
          this.onState('error', `HTTP ${response.status}`);
        } else {
          this.onState('live');
          delay = MIN_DELAY_MS;
          await this.read(response.body);
        }
      } catch (err) {
        if (this.stopped) return;
        this.onState('reconnecting', String(err));
      }
      if (!this.stopped && this.lastState === 'live') this.onState('reconnecting');
      if (this.stopped) return;
      await sleep(delay);
      delay = Math.min(2 * delay, MAX_DELAY_MS);
    }
  }

  async read(body) {
    const reader = body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = '';
    for (;;) {
      const { value, done } = await reader.read();
      if (done || this.stopped) return;
      buffer += value;
      let end;
      while ((end = buffer.indexOf('\n\n')) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end + 2);
        let name = 'message';
        let data = '';
        for (const line of block.split('\n')) {
          if (line.startsWith('event: ')) name = line.slice(7);
          else if (line.startsWith('data: ')) data += line.slice(6);
        }
        if (data) this.onEvent(name, JSON.parse(data));
      }
    }
  }
}
