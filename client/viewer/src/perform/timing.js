// Rolling per-frame timings for the page's stats (model time, latency, drawing): the
// last n values, their mean, a quantile and the max. No DOM.

/** The last n values of a per-frame timing: mean, quantile, max. */
export class Rolling {
  constructor(n) {
    this.values = new Float64Array(n);
    this.n = 0;
    this.i = 0;
  }
  push(v) {
    this.values[this.i] = v;
    this.i = (this.i + 1) % this.values.length;
    this.n = Math.min(this.n + 1, this.values.length);
  }
  mean() {
    let s = 0;
    for (let j = 0; j < this.n; j++) s += this.values[j];
    return this.n ? s / this.n : null;
  }
  quantile(q) {
    if (!this.n) return null;
    const sorted = Float64Array.from(this.values.subarray(0, this.n)).sort();
    return sorted[Math.min(this.n - 1, Math.floor(q * this.n))];
  }
  max() {
    return this.n ? Math.max(...this.values.subarray(0, this.n)) : null;
  }
}
