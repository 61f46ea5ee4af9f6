// The frame count and rate of an MP4 (or MOV) video from its header boxes, read in slices so a
// large upload is never loaded whole: the browser's <video> tells the duration but not the frames.

const MAX_TOP_BOXES = 64; // ftyp, moov, mdat, free, ...: real files have a handful
const MAX_MOOV_BYTES = 64 * 1024 * 1024; // a moov this large is not a video we can judge here

async function bytes(file, start, end) {
  return new DataView(await file.slice(start, end).arrayBuffer());
}

const fourcc = (view, at) => String.fromCharCode(...[0, 1, 2, 3].map((i) => view.getUint8(at + i)));

/** Child boxes of view[start, end): [{type, start, end}] with start past the header. */
function children(view, start, end) {
  const out = [];
  for (let at = start; at + 8 <= end;) {
    let size = view.getUint32(at), header = 8;
    if (size === 1) { size = Number(view.getBigUint64(at + 8)); header = 16; } else if (size === 0) size = end - at;
    if (size < header || at + size > end) break;
    out.push({ type: fourcc(view, at + 4), start: at + header, end: at + size });
    at += size;
  }
  return out;
}

const child = (view, box, type) => children(view, box.start, box.end).find((b) => b.type === type);

/** {frames, fps} of the first video track, or null when the file is not an MP4 this can read. */
export async function mp4Frames(file) {
  try {
    let at = 0, moov = null;
    for (let i = 0; i < MAX_TOP_BOXES && at + 16 <= file.size && !moov; i++) {
      const head = await bytes(file, at, at + 16);
      let size = head.getUint32(0);
      if (size === 1) size = Number(head.getBigUint64(8)); else if (size === 0) size = file.size - at;
      if (size < 8) return null;
      if (fourcc(head, 4) === "moov") moov = size <= MAX_MOOV_BYTES ? await bytes(file, at, at + size) : null;
      at += size;
    }
    if (!moov) return null;
    for (const trak of children(moov, 8, moov.byteLength).filter((b) => b.type === "trak")) {
      const mdia = child(moov, trak, "mdia");
      const hdlr = mdia && child(moov, mdia, "hdlr");
      if (!hdlr || fourcc(moov, hdlr.start + 8) !== "vide") continue;
      const mdhd = child(moov, mdia, "mdhd");
      const stbl = child(moov, child(moov, mdia, "minf") || mdia, "stbl");
      const stsz = stbl && child(moov, stbl, "stsz");
      if (!mdhd || !stsz) return null;
      const v1 = moov.getUint8(mdhd.start) === 1;
      const timescale = moov.getUint32(mdhd.start + (v1 ? 20 : 12));
      const duration = v1 ? Number(moov.getBigUint64(mdhd.start + 24)) : moov.getUint32(mdhd.start + 16);
      const frames = moov.getUint32(stsz.start + 8);
      return { frames, fps: duration > 0 ? (frames * timescale) / duration : null };
    }
    return null;
  } catch {
    return null; // a truncated or odd file: the server probes it anyway
  }
}
