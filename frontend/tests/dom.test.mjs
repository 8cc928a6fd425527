import { test } from "node:test";
import assert from "node:assert/strict";
import { esc, stageSummary, formatSeconds } from "../js/dom.js";

test("esc turns every HTML-significant character into an entity", () => {
  assert.equal(esc(`<img src=x onerror="alert('1')">`), "&lt;img src=x onerror=&quot;alert(&#39;1&#39;)&quot;&gt;");
  assert.equal(esc("a & b `c`"), "a &amp; b &#96;c&#96;");
});

test("esc leaves plain names alone and accepts non-strings", () => {
  assert.equal(esc("sheet-fast 2"), "sheet-fast 2");
  assert.equal(esc(42), "42");
  assert.equal(esc(null), "");
  assert.equal(esc(undefined), "");
});

test("stageSummary merges a stage's passes into one entry with their count and seconds", () => {
  const stages = [["frames", 2.2], ["register", 3.4], ["register, pass 2", 0.2], ["register, pass 3", 0.4], ["points", 1]];
  assert.equal(stageSummary(stages), "frames 2 s · register ×3 4 s · points 1 s");
  assert.equal(stageSummary([]), "");
  assert.equal(stageSummary(undefined), "");
});

test("formatSeconds reads as a person would say it", () => {
  assert.equal(formatSeconds(29.6), "30 s");
  assert.equal(formatSeconds(185), "3 min 05 s");
  assert.equal(formatSeconds(3720), "1 h 02 min");
});
