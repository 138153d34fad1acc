"""Do fragments of one fresco resemble each other more than fragments of different frescoes?

Measured the same way on RePAIR (``../shared/data/repair-dev``: its four placed objects) and on
collections of the factory's walls (``generate_wall(..., preset="pompeii", palette_seed=...)``):
for every fragment-level statistic of :mod:`common.matching.fresco` (plaster colour, its spread,
painted share, palette, grain, size), the median absolute difference between fragments of one
fresco and of different frescoes, and the AUC of "different pairs differ more than same pairs"
(0.5: the statistic does not tell frescoes apart). Then the same-fresco log-likelihood ratio
(:func:`common.matching.fresco.fit_fresco_llr`) is fitted on synthetic collections only and its
AUC on RePAIR printed beside.

    python tests/bench/bench_fresco.py [--repair ../shared/data/repair-dev] [--fit] [--cache DIR]
        [--house-plaster] [--overrides JSON] [--train "41,42,43,44p5;..."] [--test "51,52,53,54p7;..."]

Collections are given as wall seeds, ``p``, the palette seed (``41,42,43,44p5``, or a palette per wall:
``41p5,42p5,43p6,44p6``); ``;`` separates collections (pairs are only formed within one). ``--fit`` fits the ratio on the training collections and prints it with its
AUC on every set: :data:`common.matching.fresco.FRESCO_LLR` is the output of
``--fit --house-plaster --overrides '{"fade_fraction": 0.0, "discolour_fraction": 0.0}'`` (the defaults'
collections).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.matching import fresco as F  # noqa: E402

SCALES = (0.5, 1.0, 2.0, 4.0)


def _auc(within, between):
    """P(a between-fresco difference > a within-fresco difference), ties half."""
    w, b = np.asarray(within, float), np.asarray(between, float)
    w, b = w[np.isfinite(w)], b[np.isfinite(b)]
    if not len(w) or not len(b):
        return float("nan")
    return float(((b[:, None] > w[None, :]).mean() + 0.5 * (b[:, None] == w[None, :]).mean()))


def piece_stats(rgba, pixel_mm):
    s = F.image_signature(rgba, pixel_mm)
    g = F.grain_energies(rgba, pixel_mm, SCALES)
    area = float((rgba[..., 3] >= 128).sum()) * pixel_mm ** 2
    return s, g, np.sqrt(area)


def statistics_table(sigs, grains, sizes, groups, values=None, collections=None):
    """Per statistic: median |Δ| within / between frescoes (pairs within one collection), AUC."""
    g = np.asarray(groups)
    i, j, _ = F._pairs(groups, collections)
    same = g[i] == g[j]
    rows = {}

    def add(name, d):
        d = np.asarray(d, float)
        rows[name] = (float(np.nanmedian(d[same])), float(np.nanmedian(d[~same])), _auc(d[same], d[~same]))

    L = np.array([s.plaster_lab for s in sigs])
    add("a*b* histogram (Bhattacharyya distance)", [F.chroma_distance(sigs[a], sigs[b]) for a, b in zip(i, j)])
    add("plaster L* (ΔL*)", np.abs(L[i, 0] - L[j, 0]))
    add("plaster a*b* (Δa*b*)", np.hypot(L[i, 1] - L[j, 1], L[i, 2] - L[j, 2]))
    add("plaster ΔE*ab", np.linalg.norm(L[i] - L[j], axis=1))
    sp = np.array([s.plaster_spread_l for s in sigs])
    add("plaster spread L* (Δ)", np.abs(sp[i] - sp[j]))
    ps = np.array([s.painted_share for s in sigs])
    add("painted share (Δ)", np.abs(ps[i] - ps[j]))
    add("palette distance (ΔE, both painted)", [F.palette_distance(sigs[a], sigs[b]) for a, b in zip(i, j)])
    if values is not None:   # the features stage's fragment-level colour cues (whole face, paint included)
        from common.matching.pairs import _descs

        keys = [d.key for d in _descs()[0]]
        V = np.asarray(values, float)
        rgb = V[:, [keys.index(f"fragment.colour_mean_{c}") for c in "rgb"]]
        lab = F._lab_from_linear(rgb)
        add("face mean colour L* (features; Δ)", np.abs(lab[i, 0] - lab[j, 0]))
        add("face mean colour a*b* (features; Δ)", np.hypot(lab[i, 1] - lab[j, 1], lab[i, 2] - lab[j, 2]))
        cv = np.log(V[:, keys.index("fragment.colour_variance")])
        add("face colour variance (features; Δ log)", np.abs(cv[i] - cv[j]))
        sat = V[:, keys.index("fragment.saturation")]
        add("face saturation (features; Δ)", np.abs(sat[i] - sat[j]))
    if grains is not None:
        G = np.log(np.asarray(grains))
        for k, s in enumerate(SCALES):
            add(f"grain {s:g} mm (Δ log RMS L*)", np.abs(G[i, k] - G[j, k]))
    if sizes is not None:
        S = np.log(np.asarray(sizes))
        add("size √area (Δ log)", np.abs(S[i] - S[j]))
    return rows, int(same.sum()), int((~same).sum())


def llr_auc(sigs, groups, params, collections=None):
    g = np.asarray(groups)
    i, j, _ = F._pairs(groups, collections)
    same = g[i] == g[j]
    r = np.array([F.fresco_llr(sigs[a], sigs[b], params) for a, b in zip(i, j)])
    # the LLR should be higher for same pairs
    return _auc(-r[same], -r[~same]), float(np.median(r[same])), float(np.median(r[~same]))


def _face(values):
    from common.matching.pairs import _descs

    keys = [d.key for d in _descs()[0]]
    return np.asarray(values)[[keys.index(f"fragment.colour_mean_{c}") for c in "rgb"]]


def repair_data(path, cache):
    from common.matching.collection import collection_wall
    from common.matching.online import wall_cues
    from common.synth.stats import read_collection

    f = cache / "repair.pkl" if cache else None
    if f and f.exists():
        return pickle.loads(f.read_bytes())
    pieces = [p for p in read_collection(path) if p.matrix is not None]
    pm = 25.4 / 150.0
    img = [piece_stats(p.rgba, pm) for p in pieces]
    wall = collection_wall(path, dpi=150.0)
    keep = [fr for fr in wall.fragments if not fr.spurious]
    wall.fragments = keep
    tables, cues, _ = wall_cues(wall)
    out = dict(groups=[p.object for p in pieces], img=img, prof_groups=[fr.notes["object"] for fr in keep],
               profiles=[tables[fr.id].boundary_profile for fr in keep], values=[cues[fr.id].values for fr in keep])
    if f:
        f.write_bytes(pickle.dumps(out))
    return out


def factory_data(walls, cache, tag, house_plaster=False, overrides=None):
    """Walls = list of (seed, palette_seed); fragments of the walls (spurious ones left out)."""
    from common.matching.online import wall_cues
    from common.synth.stats import wall_collection
    from common.synth.wall import generate_wall

    f = cache / f"factory_{tag}.pkl" if cache else None
    if f and f.exists():
        return pickle.loads(f.read_bytes())
    groups, img, profiles, values = [], [], [], []
    for seed, pal in walls:
        w = generate_wall(16, seed=seed, dpi=75, preset="pompeii", colour_only=True, palette_seed=pal,
                          **({"house_plaster": True} if house_plaster else {}), **(overrides or {}))
        w.fragments = [fr for fr in w.fragments if not fr.spurious and fr.rgbn is not None]
        for p in wall_collection(w):
            img.append(piece_stats(p.rgba, 25.4 / 75))
        tables, cues, _ = wall_cues(w)
        profiles += [tables[fr.id].boundary_profile for fr in w.fragments]
        values += [cues[fr.id].values for fr in w.fragments]
        groups += [w.id] * len(w.fragments)
    out = dict(groups=groups, img=img, prof_groups=groups, profiles=profiles, values=values)
    if f:
        f.write_bytes(pickle.dumps(out))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repair", default=str(Path(__file__).resolve().parents[3] / "shared/data/repair-dev"))
    ap.add_argument("--fit", action="store_true", help="fit the ratio on the synthetic collections and print it")
    ap.add_argument("--cache", default=None, help="directory to cache the extracted signatures in")
    ap.add_argument("--train", default="41,42,43,44p5;45,46,47,48p6;61,62,64,69p11;65,66,67,68p12",
                    help="fitting collections: wall seeds p palette seed, collections separated by ';'")
    ap.add_argument("--test", default="51,52,53,54p7;55,56,57,58p8", help="test collections, as --train")
    ap.add_argument("--overrides", default="{}", help="JSON: further generate_wall preset overrides")
    ap.add_argument("--house-plaster", action="store_true",
                    help="the factory's walls of one palette share their plaster (generate_wall house_plaster)")
    args = ap.parse_args(argv)
    cache = Path(args.cache) if args.cache else None
    if cache:
        cache.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.time(), time.process_time()
    sets = {}
    if Path(args.repair).is_dir():
        sets["RePAIR"] = repair_data(args.repair, cache)
    ov = json.loads(args.overrides)
    h = (" house" if args.house_plaster else "") + "".join(f" {k}={v}" for k, v in sorted(ov.items()))
    for tag, spec in (("train", args.train), ("test", args.test)):
        parts = []
        for k, coll in enumerate(spec.split(";")):
            if coll.count("p") > 1:   # every wall with its own palette: "41p5,42p5,43p6,44p6"
                walls = [tuple(int(v) for v in w.split("p")) for w in coll.split(",")]
            else:                     # one palette for the collection: "41,42,43,44p5"
                seeds, pal = coll.split("p")
                walls = [(int(x), int(pal)) for x in seeds.split(",")]
            d = factory_data(walls, cache, h.replace(" ", "_") + "_" + "_".join(f"{s}p{p}" for s, p in walls),
                             args.house_plaster, ov)
            parts.append(dict(d, collections=[k] * len(d["groups"])))
        sets[f"factory{h} {tag} {spec}"] = {key: sum((p[key] for p in parts), []) for key in parts[0]}
    for d in sets.values():
        d["prof"] = [F.profile_signature(p, face_rgb=_face(v)) for p, v in zip(d["profiles"], d["values"])]
    tables = {}
    for name, d in sets.items():
        sigs = [s for s, _, _ in d["img"]]
        tables[name + " (image)"] = statistics_table(sigs, [g for _, g, _ in d["img"]], [z for _, _, z in d["img"]],
                                                   d["groups"], collections=d.get("collections"))
        tables[name + " (profile)"] = statistics_table(d["prof"], None, None, d["prof_groups"], d.get("values"),
                                                     collections=d.get("collections"))
    names = list(tables)
    stats = list(dict.fromkeys(k for t in tables.values() for k in t[0]))
    print("| statistic | " + " | ".join(f"{n}: within / between, AUC" for n in names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for s in stats:
        cells = []
        for n in names:
            r = tables[n][0].get(s)
            cells.append("—" if r is None else f"{r[0]:.2f} / {r[1]:.2f}, {r[2]:.2f}")
        print(f"| {s} | " + " | ".join(cells) + " |")
    print("| pairs same / different | " + " | ".join(f"{tables[n][1]} / {tables[n][2]}" for n in names) + " |")
    if args.fit:
        train = next(d for n, d in sets.items() if n.startswith("factory") and " train " in n)
        for feats in (F.LLR_FEATURES, F.PAIR_FEATURES):
            params = F.fit_fresco_llr(train["prof"], train["prof_groups"], collections=train["collections"],
                                      features=feats)
            print("FRESCO_LLR =", json.dumps({k: (np.round(v, 4).tolist() if isinstance(v, list) and k != "features"
                                                  else v) for k, v in params.items()}))
            for name, d in sets.items():
                auc, ms, md = llr_auc(d["prof"], d["prof_groups"], params, d.get("collections"))
                print(f"  LLR on {name} (profile): AUC same > different {auc:.3f}; median LLR same {ms:+.2f}, "
                      f"different {md:+.2f}")
    print(f"{time.time() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU", flush=True)


if __name__ == "__main__":
    main()
