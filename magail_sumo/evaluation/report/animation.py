"""Animated per-scene view for the HTML report: the log and each method's first rollout side by
side, agents as oriented boxes, traffic-light states on the map, play / pause / scrub.

Self-contained: one ``<canvas>`` per panel, the trajectories as inline JSON and a small script
(no external files, no network). Frame 0 is the scene's current step (the last logged state),
frames 1..T the simulated steps at 10 Hz. States the log or a method marks invalid are absent
(``null``) and not drawn. The player autoplays in a loop and writes the frame shown to the
container's ``data-frame`` attribute (headless-browser tests read it).
"""

from __future__ import annotations

import html
import json

import numpy as np

from magail_sumo.outputs import printable
from magail_sumo.scene import ObjectType, SignalState

from .scores import Scores

#: Signal states drawn red / yellow / green (the rest grey).
_RED = {SignalState.STOP, SignalState.ARROW_STOP, SignalState.FLASHING_STOP}
_YELLOW = {SignalState.CAUTION, SignalState.ARROW_CAUTION, SignalState.FLASHING_CAUTION}
_GREEN = {SignalState.GO, SignalState.ARROW_GO}


def _signal_code(state: int) -> int:
    """0 unknown, 1 red, 2 yellow, 3 green."""
    s = SignalState(int(state))
    return 1 if s in _RED else 2 if s in _YELLOW else 3 if s in _GREEN else 0


def _coords(a: np.ndarray, valid: np.ndarray | None = None, nd: int = 1) -> list:
    """Rounded values with ``None`` where not valid or not finite."""
    a = np.round(np.asarray(a, np.float64), nd)
    ok = np.isfinite(a) if valid is None else (np.asarray(valid, bool) & np.isfinite(a))
    return [float(v) if o else None for v, o in zip(a.tolist(), ok.tolist())]


def _clip_lines(lines: list[np.ndarray], box: tuple[float, float, float, float],
                step: int = 2) -> list[list[float]]:
    """Polylines that touch ``box`` (xmin, ymin, xmax, ymax), every ``step``-th point kept
    (ends kept), flattened [x0, y0, x1, y1, ...] and rounded to 0.1 m."""
    x0, y0, x1, y1 = box
    out = []
    for ln in lines:
        p = np.asarray(ln)[:, :2]
        if p.shape[0] < 2:
            continue
        inside = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        if not inside.any():
            continue
        idx = np.unique(np.r_[np.arange(0, len(p), step), len(p) - 1])
        out.append(np.round(p[idx], 1).ravel().tolist())
    return out


def scene_data(scores: Scores, sid: str, pad: float = 30.0) -> dict:
    """The JSON the player draws for one scene (see the module doc)."""
    scene = scores.scenes[sid]
    tr = scene.tracks
    cur = scene.current_time_index
    methods = [m for m in scores.methods if (sid, m) in scores.rollouts]
    ro0 = scores.rollouts[(sid, methods[0])]
    ids = ro0.object_id
    rows = np.array([int(np.flatnonzero(tr.id == i)[0]) for i in ids])
    T = ro0.shape[2]
    frames = slice(cur, cur + 1 + T)
    v_now = tr.valid[rows, cur]
    xs, ys = tr.x[rows, cur][v_now], tr.y[rows, cur][v_now]
    if xs.size == 0:
        xs, ys = np.zeros(1), np.zeros(1)
    box = (float(xs.min() - pad), float(ys.min() - pad), float(xs.max() + pad),
           float(ys.max() + pad))
    last = np.where(tr.valid[rows, : cur + 1], np.arange(cur + 1), -1).max(1)
    size_at = np.maximum(last, 0)
    agents = [{"id": int(i), "type": ObjectType(int(tr.type[r])).name.lower(),
               "sdc": bool(r == scene.sdc_track_index),
               "l": round(float(tr.length[r, s]), 2), "w": round(float(tr.width[r, s]), 2)}
              for i, r, s in zip(ids, rows, size_at)]

    def panel(name: str, x: np.ndarray, y: np.ndarray, h: np.ndarray,
              valid: np.ndarray) -> dict:
        return {"name": name, "x": [_coords(a, v) for a, v in zip(x, valid)],
                "y": [_coords(a, v) for a, v in zip(y, valid)],
                "h": [_coords(a, v, 2) for a, v in zip(h, valid)]}

    n_log = tr.x[rows, frames].shape[1]
    pad_t = T + 1 - n_log  # a log shorter than current + T: the rest is absent

    def logged(a: np.ndarray) -> np.ndarray:
        return np.pad(a[rows, frames].astype(np.float64), ((0, 0), (0, pad_t)),
                      constant_values=np.nan)

    log_valid = np.pad(tr.valid[rows, frames], ((0, 0), (0, pad_t)))
    panels = [panel("log", logged(tr.x), logged(tr.y), logged(tr.heading), log_valid)]
    for m in methods:
        ro = scores.rollouts[(sid, m)]
        if not np.array_equal(ro.object_id, ids):
            continue
        valid = scores.valid.get((sid, m))
        sim_valid = np.ones((len(ids), T), bool) if valid is None else valid[0]
        now = lambda a: a[rows, cur][:, None].astype(np.float64)  # noqa: E731
        panels.append(panel(m, np.hstack([now(tr.x), ro.x[0]]), np.hstack([now(tr.y), ro.y[0]]),
                            np.hstack([now(tr.heading), ro.heading[0]]),
                            np.hstack([v_now[:, None], sim_valid])))
    sig = scene.signals
    signals = []
    if len(sig):
        for lane in np.unique(sig.lane).tolist():
            sel = sig.lane == lane
            steps, states = sig.step[sel], sig.state[sel]
            pt = sig.stop_point[sel][0]
            if not (box[0] <= pt[0] <= box[2] and box[1] <= pt[1] <= box[3]):
                continue
            code = [0] * (T + 1)
            for st, s in zip(steps.tolist(), states.tolist()):
                if cur <= st <= cur + T:
                    code[st - cur] = _signal_code(s)
            signals.append({"x": round(float(pt[0]), 1), "y": round(float(pt[1]), 1),
                            "s": code})
    return {"scenario_id": sid, "dt": 0.1, "frames": T + 1, "box": [round(b, 1) for b in box],
            "lanes": _clip_lines([ln.polyline for ln in scene.roadmap.lanes], box),
            "edges": _clip_lines([e.polyline for e in scene.roadmap.road_edges], box),
            "signals": signals, "agents": agents, "panels": panels}


def _json_for_script(obj: object) -> str:
    """JSON that cannot end the ``<script>`` element it sits in."""
    return (json.dumps(obj, separators=(",", ":"), allow_nan=False)
            .replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026"))


CSS = """.anim{margin:1em 0}.anim .panels{display:flex;flex-wrap:wrap;gap:6px}
.anim figure{margin:0}.anim figcaption{font-size:12px;text-align:center}
.anim canvas{border:1px solid #bbb;background:#fafafa}
.anim .ctl{display:flex;align-items:center;gap:8px;font-size:13px;margin:4px 0}
.anim .ctl input{width:320px}"""

#: The player (one copy per page): draws every ``.anim`` element from its JSON.
SCRIPT = r"""
(function(){
const COL={vehicle:'#1f77b4',pedestrian:'#ff7f0e',cyclist:'#2ca02c',other:'#8c564b',unset:'#8c564b'};
const SIG=['#999999','#d62728','#f0b400','#2ca02c'];
function setup(root){
  const d=JSON.parse(root.querySelector('script[type="application/json"]').textContent);
  const box=d.box, W=280, sc=W/Math.max(box[2]-box[0],box[3]-box[1]);
  const H=Math.round((box[3]-box[1])*sc), Wc=Math.round((box[2]-box[0])*sc);
  const P=(x,y)=>[(x-box[0])*sc,(box[3]-y)*sc];
  const wrap=root.querySelector('.panels'); const ctx=[];
  for(const p of d.panels){
    const f=document.createElement('figure'), c=document.createElement('canvas');
    c.width=Wc; c.height=H; const cap=document.createElement('figcaption');
    cap.textContent=p.name; f.appendChild(c); f.appendChild(cap); wrap.appendChild(f);
    ctx.push(c.getContext('2d'));
  }
  const slider=root.querySelector('input'), btn=root.querySelector('button'),
        lab=root.querySelector('.t');
  slider.max=d.frames-1;
  function lines(g,ls,col,w){g.strokeStyle=col;g.lineWidth=w;g.beginPath();
    for(const l of ls){for(let i=0;i<l.length;i+=2){const q=P(l[i],l[i+1]);
      if(i===0)g.moveTo(q[0],q[1]);else g.lineTo(q[0],q[1]);}}g.stroke();}
  function draw(t){
    d.panels.forEach((p,k)=>{const g=ctx[k];g.clearRect(0,0,Wc,H);
      lines(g,d.lanes,'#cccccc',1);lines(g,d.edges,'#333333',1.2);
      for(const s of d.signals){const q=P(s.x,s.y);g.fillStyle=SIG[s.s[t]];g.beginPath();
        g.arc(q[0],q[1],3.5,0,2*Math.PI);g.fill();}
      d.agents.forEach((a,i)=>{
        // trail of past frames
        g.strokeStyle=COL[a.type]||'#555';g.globalAlpha=0.35;g.lineWidth=1;g.beginPath();
        let on=false;for(let u=0;u<=t;u++){const x=p.x[i][u],y=p.y[i][u];
          if(x===null||y===null){on=false;continue;}const q=P(x,y);
          if(on)g.lineTo(q[0],q[1]);else g.moveTo(q[0],q[1]);on=true;}
        g.stroke();g.globalAlpha=1;
        const x=p.x[i][t],y=p.y[i][t],h=p.h[i][t];
        if(x===null||y===null||h===null)return;
        const q=P(x,y);g.save();g.translate(q[0],q[1]);g.rotate(-h);
        g.fillStyle=a.sdc?'#d62728':(COL[a.type]||'#555');
        g.fillRect(-a.l*sc/2,-a.w*sc/2,Math.max(a.l*sc,2),Math.max(a.w*sc,2));g.restore();});
    });
    slider.value=t; lab.textContent='t = +'+(t*d.dt).toFixed(1)+' s';
    root.dataset.frame=t;
  }
  let t=0, timer=null;
  function play(){if(timer)return;btn.textContent='pause';
    timer=setInterval(()=>{t=(t+1)%d.frames;draw(t);},100);}
  function pause(){clearInterval(timer);timer=null;btn.textContent='play';}
  btn.onclick=()=>timer?pause():play();
  slider.oninput=()=>{pause();t=+slider.value;draw(t);};
  draw(0); play();
}
document.querySelectorAll('.anim').forEach(setup);
})();
"""


def scene_animation(scores: Scores, sid: str) -> str:
    """The HTML fragment of one scene's player (its JSON inline; :data:`SCRIPT` runs it)."""
    data = scene_data(scores, sid)
    return (f'<div class="anim" data-scene="{html.escape(printable(sid, 200))}" data-frame="0">'
            f'<div class="ctl"><button type="button">play</button>'
            f'<input type="range" min="0" max="{data["frames"] - 1}" value="0">'
            f'<span class="t"></span><span>log (left) vs first rollout of each method; red '
            f'box: SDC; dots: traffic lights</span></div><div class="panels"></div>'
            f'<script type="application/json">{_json_for_script(data)}</script></div>')
