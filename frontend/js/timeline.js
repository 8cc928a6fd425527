// Time in the viewer: the slider and its label (frame, seconds, t), the training frames' times
// that frame steps snap to, and play/pause. Mixed into `Viewer`.

import { $ } from "./dom.js";

export const timeline = {
  setTime(t, fromSlider = false) {
    this.t = Math.min(1, Math.max(0, t));
    if (!fromSlider) $("time").value = Math.round(this.t * 1000);
    const times = this.frameTimes(), k = this.nearestFrame();
    const at = times.length && Math.abs(times[k] - this.t) < 1e-6 ? "frame" : "near frame";
    // Seconds into the clip when its frame rate is known (frame times run 0 to 1 over it).
    const rate = this.meta.frame_rate;
    const secs = rate && times.length > 1 ? ` · ${(this.t * (times.length - 1) / rate).toFixed(2)} s` : "";
    $("time-label").textContent = times.length ? `${at} ${k + 1} of ${times.length}${secs} · t = ${this.t.toFixed(3)}`
      : `t = ${this.t.toFixed(3)}`;
    this.requestTime();
  },

  // The training camera's frame times, in order (what frame steps snap to).
  frameTimes() {
    if (!this._frameTimes) {
      const train = this.meta.frames.filter((f) => f.split === "train" && (f.camera_id || 0) === 0);
      this._frameTimes = [...new Set((train.length ? train : this.meta.frames).map((f) => f.time))].sort((a, b) => a - b);
    }
    return this._frameTimes;
  },

  nearestFrame() {
    const times = this.frameTimes();
    let best = 0;
    times.forEach((t, k) => { if (Math.abs(t - this.t) < Math.abs(times[best] - this.t)) best = k; });
    return best;
  },

  // One frame back or forward, onto the frame's own time (from between two frames, to the next).
  stepFrame(dir) {
    const times = this.frameTimes();
    if (!times.length) return this.setTime(this.t + dir * this.meta.dt);
    const k = this.nearestFrame();
    const off = Math.abs(times[k] - this.t) < 1e-6 ? dir : (Math.sign(times[k] - this.t) === dir ? 0 : dir);
    this.setTime(times[Math.min(times.length - 1, Math.max(0, k + off))]);
  },

  // Playback by `dt` seconds at 30 frames a second times the speed; the clip's last moment is
  // shown before it loops, however long a frame took.
  advancePlayback(dt) {
    const duration = Math.max(1, this.frameTimes().length) / 30;
    this.setTime(this.t >= 1 ? 0 : Math.min(1, this.t + (dt * this.speed) / duration));
  },

  togglePlay() {
    this.playing = !this.playing;
    $("play").textContent = this.playing ? "Pause" : "Play";
  },
};
