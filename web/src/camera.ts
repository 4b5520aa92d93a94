import { Link, wsUrl } from "./connection";
import { num, type StateMessage } from "./types";

/** Overlay data the server may add to state messages for the camera view. */
interface CameraOverlay {
  width_px?: number;
  height_px?: number;
  found?: boolean;
  x_px?: number;
  y_px?: number;
  r_px?: number;
  predicted_px?: number[][];
  intercept_px?: number[];
}

/**
 * The camera view: JPEG frames from `/ws/camera` with overlays (detected ball,
 * predicted positions, intercept point) drawn on a canvas above the image.
 */
export class CameraView {
  private readonly img: HTMLImageElement;
  private readonly overlay: HTMLCanvasElement;
  private url: string | null = null;
  private link: Link;
  frames = 0;
  private latest: StateMessage | null = null;

  constructor(host: HTMLElement) {
    this.img = host.querySelector("img") as HTMLImageElement;
    this.overlay = host.querySelector("canvas") as HTMLCanvasElement;
    this.link = new Link(wsUrl("/ws/camera"), () => {}, (s) => host.classList.toggle("offline", s !== "open"), (blob) => this.frame(blob));
    this.link.start();
  }

  private frame(blob: Blob): void {
    const next = URL.createObjectURL(blob);
    this.img.onload = () => {
      if (this.url && this.url !== next) URL.revokeObjectURL(this.url);
      this.url = next;
    };
    this.img.src = next;
    this.img.hidden = false;
    this.frames += 1;
  }

  update(s: StateMessage): void {
    this.latest = s;
  }

  draw(): void {
    const cam = (this.latest as unknown as { camera?: CameraOverlay } | null)?.camera;
    const c = this.overlay;
    const w = this.img.naturalWidth || cam?.width_px || 1280;
    const h = this.img.naturalHeight || cam?.height_px || 720;
    if (c.width !== w || c.height !== h) {
      c.width = w;
      c.height = h;
    }
    const ctx = c.getContext("2d");
    if (!ctx) return;
    ctx.clearRect(0, 0, w, h);
    if (!cam) return;
    ctx.lineWidth = Math.max(2, w / 400);
    if (cam.found && Number.isFinite(num(cam.x_px))) {
      ctx.strokeStyle = "#D55E00";
      ctx.beginPath();
      ctx.arc(num(cam.x_px), num(cam.y_px), Math.max(4, num(cam.r_px)), 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.fillStyle = "rgba(0,114,178,0.8)";
    for (const p of cam.predicted_px ?? []) {
      ctx.beginPath();
      ctx.arc(p[0], p[1], 3, 0, 2 * Math.PI);
      ctx.fill();
    }
    if (cam.intercept_px && cam.intercept_px.length === 2) {
      const [x, y] = cam.intercept_px;
      ctx.strokeStyle = "#009E73";
      ctx.beginPath();
      ctx.moveTo(x - 12, y);
      ctx.lineTo(x + 12, y);
      ctx.moveTo(x, y - 12);
      ctx.lineTo(x, y + 12);
      ctx.stroke();
    }
  }
}
