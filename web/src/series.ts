/**
 * A fixed-capacity sliding window of aligned columns for uPlot.
 *
 * Storage is allocated once; pushing shifts in place, so streaming for hours
 * does not grow the heap.
 */
export class SeriesWindow {
  readonly capacity: number;
  private readonly cols: Float64Array[];
  private len = 0;
  private readonly views: Float64Array[];
  private readonly plain: (number | null)[][];

  constructor(columns: number, capacity: number) {
    if (!Number.isInteger(columns) || columns < 1) throw new Error("columns must be >= 1");
    if (!Number.isInteger(capacity) || capacity < 2) throw new Error("capacity must be >= 2");
    this.capacity = capacity;
    this.cols = Array.from({ length: columns }, () => new Float64Array(capacity));
    this.views = this.cols.map((c) => c.subarray(0, 0));
    this.plain = this.cols.map(() => []);
  }

  /** Number of rows held. */
  get length(): number {
    return this.len;
  }

  /** Appends one row (column 0 is x, usually time); drops the oldest when full. */
  push(row: readonly number[]): void {
    if (row.length !== this.cols.length) throw new Error(`row has ${row.length} values, expected ${this.cols.length}`);
    if (this.len === this.capacity) {
      for (const c of this.cols) c.copyWithin(0, 1);
      this.len -= 1;
    }
    for (let i = 0; i < row.length; i++) this.cols[i][this.len] = row[i];
    this.len += 1;
    for (let i = 0; i < this.cols.length; i++) this.views[i] = this.cols[i].subarray(0, this.len);
  }

  /** Forgets every row. */
  clear(): void {
    this.len = 0;
    for (let i = 0; i < this.cols.length; i++) this.views[i] = this.cols[i].subarray(0, 0);
  }

  /** The columns, oldest first (views into the storage, valid until the next push). */
  data(): Float64Array[] {
    return this.views;
  }

  /**
   * The columns as uPlot wants them: plain arrays with `null` for gaps (NaN would
   * poison uPlot's axis ranges). The arrays are reused from call to call.
   */
  plotData(): (number | null)[][] {
    for (let i = 0; i < this.cols.length; i++) {
      const out = this.plain[i];
      const col = this.cols[i];
      out.length = this.len;
      for (let k = 0; k < this.len; k++) {
        const v = col[k];
        out[k] = Number.isFinite(v) ? v : null;
      }
    }
    return this.plain;
  }

  /** The newest x value, or NaN when empty. */
  lastX(): number {
    return this.len > 0 ? this.cols[0][this.len - 1] : Number.NaN;
  }
}
