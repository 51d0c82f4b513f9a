// The depth sort off the main thread: a module Worker that packs, culls, sorts and plans one frame at a time
// (depth_sort.js `prepareFrame`). Messages: {id, gaussians, camera, limits, maxPointSize, keyBits, interval} in,
// {id, rows, runs, seconds} or {id, error} out; arrays travel as transferables. The worker keeps the sorter (and
// with a sort interval its last order) from frame to frame, as the Python runtime's splatter does.

import { DepthSorter, prepareFrame } from './depth_sort.js';

let sorter = new DepthSorter();

self.onmessage = (event) => {
  const { id, gaussians, camera, limits, maxPointSize, keyBits, interval } = event.data;
  try {
    const start = performance.now();
    if (sorter.keyBits !== keyBits || sorter.interval !== interval) sorter = new DepthSorter(interval, keyBits);
    const { rows, runs } = prepareFrame(gaussians, camera, limits, maxPointSize, sorter);
    self.postMessage({ id, rows, runs, seconds: (performance.now() - start) / 1000 }, [rows.buffer]);
  } catch (error) {
    self.postMessage({ id, error: String(error?.message ?? error) });
  }
};
