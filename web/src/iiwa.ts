/** KUKA LBR iiwa 7 R800 forward kinematics (standard DH, IIWA7.md), for the 3D twin. */

const D = [0.34, 0, 0.4, 0, 0.4, 0, 0.126];
const ALPHA = [-Math.PI / 2, Math.PI / 2, Math.PI / 2, -Math.PI / 2, -Math.PI / 2, Math.PI / 2, 0];

/** A 4x4 homogeneous transform, row-major. */
export type Mat4 = number[];

function mul(a: Mat4, b: Mat4): Mat4 {
  const r = new Array<number>(16).fill(0);
  for (let i = 0; i < 4; i++)
    for (let j = 0; j < 4; j++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[i * 4 + k] * b[k * 4 + j];
      r[i * 4 + j] = s;
    }
  return r;
}

function dh(q: number, d: number, alpha: number): Mat4 {
  const cq = Math.cos(q), sq = Math.sin(q), ca = Math.cos(alpha), sa = Math.sin(alpha);
  // Rz(q) * Tz(d) * Rx(alpha)
  return [cq, -sq * ca, sq * sa, 0, sq, cq * ca, -cq * sa, 0, 0, sa, ca, d, 0, 0, 0, 1];
}

/** The frames base, joint 1..7 (flange last): 8 transforms, base frame. */
export function frames(q: readonly number[]): Mat4[] {
  if (q.length !== 7) throw new Error("7 joint angles expected");
  const out: Mat4[] = [[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]];
  let t = out[0];
  for (let i = 0; i < 7; i++) {
    t = mul(t, dh(q[i], D[i], ALPHA[i]));
    out.push(t);
  }
  return out;
}

/** Origin of a transform. */
export function origin(t: Mat4): [number, number, number] {
  return [t[3], t[7], t[11]];
}
