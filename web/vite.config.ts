import { defineConfig } from "vitest/config";

export default defineConfig({
  server: { proxy: { "/api": "http://127.0.0.1:8080", "/ws": { target: "ws://127.0.0.1:8080", ws: true } } },
  build: {
    outDir: "dist",
    emptyOutDir: true,
    chunkSizeWarningLimit: 1200,
    // Two pages: the dashboard (/) and the demo kiosk (/demo).
    rollupOptions: { input: { main: "index.html", demo: "demo.html" } },
  },
  test: { include: ["src/**/*.test.ts"] },
});
