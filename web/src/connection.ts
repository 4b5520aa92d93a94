import { parseMessage, type ServerMessage } from "./types";

/** Connection status shown in the banner. */
export type LinkStatus = "connecting" | "open" | "lost";

/**
 * A WebSocket that reconnects by itself (backoff 0.5 s doubling to 5 s) and
 * reports its status, so the page can show a banner while the link is down.
 */
export class Link {
  private ws: WebSocket | null = null;
  private retryMs = 500;
  private timer: number | undefined;
  private stopped = false;
  /** Messages received since the page loaded. */
  received = 0;
  /** Messages that did not parse (counted, then ignored). */
  malformed = 0;

  constructor(
    private readonly url: string,
    private readonly onMessage: (m: ServerMessage) => void,
    private readonly onStatus: (s: LinkStatus) => void,
    private readonly binary?: (data: ArrayBuffer) => void,
  ) {}

  start(): void {
    this.stopped = false;
    this.open();
  }

  stop(): void {
    this.stopped = true;
    window.clearTimeout(this.timer);
    this.ws?.close();
  }

  private open(): void {
    this.onStatus("connecting");
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      this.retryMs = 500;
      this.onStatus("open");
    };
    ws.onmessage = (ev: MessageEvent) => {
      this.received += 1;
      if (typeof ev.data === "string") {
        const m = parseMessage(ev.data);
        if (m) this.onMessage(m);
        else this.malformed += 1;
      } else if (this.binary && ev.data instanceof ArrayBuffer) {
        this.binary(ev.data);
      }
    };
    ws.onclose = () => {
      if (this.stopped) return;
      this.onStatus("lost");
      this.timer = window.setTimeout(() => this.open(), this.retryMs);
      this.retryMs = Math.min(this.retryMs * 2, 5000);
    };
    ws.onerror = () => ws.close();
  }
}

/** `ws://host/path` for the page's own origin. */
export function wsUrl(path: string): string {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return `${proto}//${location.host}${path}`;
}
