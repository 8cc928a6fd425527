// Web Worker: depth sorting off the main thread. Messages in:
//   {positions: Float32Array, count, viewRow: [4], id}  -> {order: Uint32Array, id}
import { depthSort } from "./sort.js";

self.onmessage = (e) => {
  const { positions, count, viewRow, id } = e.data;
  const order = depthSort(positions, count, viewRow);
  self.postMessage({ order, id }, [order.buffer]);
};
