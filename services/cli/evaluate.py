"""``tessera evaluate``: evaluate the matcher on synthetic walls (and DAFNE) (thesis §5.8).

    tessera evaluate [--out docs/matching] [--fragments 150] [--seed 11] [--test-seed 12]
                     [--dpi 100] [--folds 10] [--classifiers logistic,tree,forest,svm]
                     [--subsets colour,curvature,normal,erosion,thickness,per-match,all]
                     [--dafne ../shared/data/dafne-adam]
    tessera evaluate --train-model ROOT [--db PATH] [--fragments 150] [--seed 11] [--dpi 100]
    tessera evaluate --collection DIR [--dpi 150] [--json FILE] [--model ROOT] [--out DIR] [--single-fresco]
                     [--fresco-weight W]

The first form writes ``table_5_3.csv`` (true/false positive/negative rates per classifier and
feature subset, 10-fold cross-validation grouped by fragment pair), precision–recall plots,
``crosswall.csv`` (train on one wall, test on another, §5.8.5), ``topk.csv``/``topk.png``
(share of each fragment's true neighbours among its k best proposals, for the station's staged
ranking and, for comparison, stage 3 by the learned combination of the stage scores fitted on the
training wall, no docking, stage 2 alone and the ribbon alone) and, with ``--dafne``, the
same for the colour-only DAFNE set. The second trains a model on a synthetic wall (the defaults
above: 150 fragments, seed 11, 100 dpi — not those of the matcher's own bootstrap, 60 fragments of
seed 0, which ``--fragments 60 --seed 0`` reproduces) and installs it as the current model of a
station's matcher (storage root ``ROOT``). The third ranks a real, placed
collection (``../shared/data/repair-dev`` layout, below) with the station's default model — the
bootstrap model, or the current model of the station at ``--model ROOT`` — fitting nothing on it,
and prints and writes pooled top-k, within-object recall with its random baseline, pair AP and
pose accuracy (docs/matching.md); its picture of hits and misses (``collection_examples.png``) goes to
``--out``, by default the folder of the ``--json`` file, or the current folder without one.
``--single-fresco`` ranks as a station set for a collection of one fresco of mostly plain plaster does
(``[services.matcher] single_fresco``, docs/matching.md, "A ribbon at three lengths, and one fresco"; not for a
figure painting, whose boundary colours tell which part of the picture a piece is from: "One fresco richly
painted"). ``--fresco-weight W`` ranks with the same-fresco ratio's weight a station set with ``[services.matcher]
fresco_weight`` has (default 8, for several frescoes; 4 measured better on one figure painting: "The same-fresco
ratio's weight above 4").

The collection's layout (``common.synth.stats.read_collection``; docs/matching.md, "Real fragments: RePAIR"):
``DIR/<object>/<picture>``, one folder per object with ``truth.csv`` beside its pictures. Objects are the
folders directly in ``DIR`` (hidden ones and ``__MACOSX`` not); pictures are the PNG, TIFF and JPEG files
directly in an object folder, suffix in any case (hidden files such as ``._name.png``, and other files, not
read): RGBA, 8 or 16 bits, any size each; grey with or without alpha; RGB, or RGBA whose alpha is 255
everywhere, is the piece on a plain background of any colour. ``truth.csv`` (name in any case): ``rpf,x,y,rot``
in the picture's own pixels (rotate counter-clockwise by ``rot`` degrees about the picture's centre, canvas
kept, then put its top-left corner at ``(x, y)``); UTF-8 with or without BOM, UTF-16 with BOM or
Windows-1252; any line ends; comma-, semicolon- (decimal comma then allowed) or tab-separated as its header
is; column names in any case and order, spaces round cells, extra columns and blank rows ignored; ``rpf`` is
the picture's file name, its stem, a path ending in it, or the name in another case or with another picture
suffix (two pictures it could name: refused). Folders without ``truth.csv``, or with one without rows, hold
distractors. Left out with a warning naming file, line and reason, listed after the first line printed
and under ``skipped`` in the JSON (the figures are those of the rest): damaged pictures (truncated,
corrupt, empty, fully transparent, no piece on the background), ``truth.csv`` rows naming no picture, with
a value that is not a finite number, or placing a picture twice (both), an unusable ``truth.csv`` (its
object), a picture of a placed object that no row places, folders without pictures and pictures directly in
``DIR``. Refused before any work: ``DIR`` missing or a file, no object folder placing two or more of its
pictures, pictures only directly in ``DIR`` or object folders one level deeper (the folder to give is
named), a ``--json`` that is a folder, a ``--dpi`` that is not a positive number.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from common.messages import to_json

log = logging.getLogger("tessera.evaluate")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="evaluate the matcher: rates, PR curves, top-k recall (§5.8)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=None, help="directory for CSV and PNG results (default: docs/matching; with "
                                               "--collection the folder of the --json file, else the current one)")
    p.add_argument("--fragments", type=int, default=150, help="fragments per synthetic wall (default 150)")
    p.add_argument("--seed", type=int, default=11, help="seed of the training wall (default 11)")
    p.add_argument("--test-seed", type=int, default=12, help="seed of the test wall (default 12)")
    p.add_argument("--dpi", type=float, default=None,
                   help="sampling of the synthetic fragments (default 100), or the nominal dpi of a --collection's "
                        "images (default 150)")
    p.add_argument("--folds", type=int, default=10, help="cross-validation folds (default 10)")
    p.add_argument("--classifiers", default="logistic,tree,forest,svm", help="classifiers compared on all features")
    p.add_argument("--subsets", default="colour,curvature,normal,erosion,thickness,per-match,all",
                   help="feature subsets for the logistic regression")
    p.add_argument("--negatives", type=float, default=10.0, help="sampled non-matches per match (default 10)")
    p.add_argument("--dafne", help="a DAFNE set (e.g. ../shared/data/dafne-adam): colour-only evaluation")
    p.add_argument("--train-model", metavar="ROOT", help="train a model on a synthetic wall (--fragments, default "
                                                         "150; --seed, default 11; --dpi, default 100) and install it "
                                                         "in the matcher's proposal store under storage root ROOT "
                                                         "(the matcher's own bootstrap: --fragments 60 --seed 0)")
    p.add_argument("--db", help="proposal database (default ROOT/matches/proposals.sqlite)")
    p.add_argument("--collection", metavar="DIR", help="evaluate on a real placed collection (repair-dev layout: "
                                                       "DIR/<object>/<pictures> and truth.csv rpf,x,y,rot; "
                                                       "accepted variations: docs/matching.md, Real fragments)")
    p.add_argument("--json", metavar="FILE", help="with --collection: write the figures as JSON")
    p.add_argument("--single-fresco", action="store_true",
                   help="with --collection: rank as a station set for a collection of one fresco of mostly "
                        "plain plaster "
                        "([services.matcher] single_fresco): the same-fresco ratio does not re-order candidates")
    p.add_argument("--fresco-weight", type=float, metavar="W",
                   help="with --collection: the same-fresco ratio's weight ([services.matcher] fresco_weight; default "
                        "8, best for several frescoes; 4 measured better on one figure painting; 0: off)")
    p.add_argument("--model", metavar="ROOT", help="with --collection: use the current model of the station "
                                                   "at storage root ROOT (default: the bootstrap model)")
    p.set_defaults(func=run)


def run(args) -> int:
    from common.matching.classifiers import CLASSIFIERS, SUBSETS

    def progress(fraction, text):
        log.info("%3.0f%% %s", 100 * fraction, text)

    if args.collection:
        return _collection(args, progress)
    args.dpi = 100.0 if args.dpi is None else args.dpi
    args.out = "docs/matching" if args.out is None else args.out
    if args.folds < 2:
        raise SystemExit("--folds must be at least 2")
    if args.fragments < 10:
        raise SystemExit("--fragments must be at least 10 (a wall needs neighbours to learn from)")
    if args.train_model:
        return _train(args, progress)
    kinds = [k.strip() for k in args.classifiers.split(",") if k.strip()]
    subsets = [s.strip() for s in args.subsets.split(",") if s.strip()]
    bad = [k for k in kinds if k not in CLASSIFIERS] + [s for s in subsets if s not in SUBSETS]
    if bad:
        raise SystemExit(f"unknown classifier or subset {bad}; classifiers: {list(CLASSIFIERS)}, subsets: {list(SUBSETS)}")
    if args.dafne and not Path(args.dafne).is_dir():
        raise SystemExit(f"--dafne {args.dafne}: no such directory")
    from common.matching.report import evaluate_matching
    res = evaluate_matching(args.out, n_fragments=args.fragments, seed=args.seed, test_seed=args.test_seed,
                            dpi=args.dpi, folds=args.folds, classifiers=kinds, subsets=subsets,
                            negatives_per_positive=args.negatives, dafne=args.dafne, progress=progress)
    print(f"{'classifier':10s} {'subset':10s} {'TPR':>6s} {'TNR':>6s} {'AP':>6s}")
    for r in res["table"]:
        print(f"{r['classifier']:10s} {r['subset']:10s} {r['tpr']:6.3f} {r['tnr']:6.3f} {r['ap']:6.3f}")
    for r in res["crosswall"]:
        print(f"train {r['train_wall']} -> test {r['test_wall']}: TPR {r['tpr']:.3f} TNR {r['tnr']:.3f} AP {r['ap']:.3f}")
    for name, rec in res["topk"].items():
        print(f"top-k recall, {name}: " + ", ".join(f"k={k}: {v:.3f}" for k, v in rec.items()))
    print("fragment-pair AP: " + json.dumps({k: round(v, 4) for k, v in res["pair_ap"].items()}))
    print(f"results in {args.out}")
    return 0


def _check_collection(path: Path) -> None:
    """Refuse, before any work, a collection with nothing to evaluate (no object folder placing two of its
    pictures), saying what each object folder holds; a layout without object folders is left to the reader,
    which says where the pictures are."""
    from common.synth.stats import collection_layout

    if not path.exists():
        raise SystemExit(f"--collection {path}: no such directory")
    if not path.is_dir():
        raise SystemExit(f"--collection {path}: is a file, not a directory (give the collection's folder: one "
                         "folder per object, each with its pictures and truth.csv)")
    layout = {k: v for k, v in collection_layout(path).items() if v["pictures"] or v["deeper"]}
    if any(v["pictures"] for v in layout.values()) and not any((v["placed"] or 0) >= 2 for v in layout.values()):
        def holds(v):
            if not v["pictures"]:
                return (f"no picture directly in it (its subfolder {v['deeper'][0]} holds pictures: put them directly "
                        "in the object's folder, beside its truth.csv)")
            if v["problem"]:
                return v["problem"]
            if v["placed"] is None:
                return f"{v['pictures']} pictures, no truth.csv"
            return f"{v['placed']} placed of {v['pictures']} pictures"
        shown = "; ".join(f"{k}: {holds(v)}" for k, v in list(layout.items())[:8])
        raise SystemExit(f"--collection {path}: nothing to evaluate: no object folder places two or more of its "
                         f"pictures (truth.csv rows rpf,x,y,rot naming them); {shown}"
                         + ("; ..." if len(layout) > 8 else ""))


def _collection(args, progress) -> int:
    import math

    from common.matching.report import evaluate_collection

    _check_collection(Path(args.collection))
    dpi = 150.0 if args.dpi is None else args.dpi
    if not (math.isfinite(dpi) and dpi > 0):
        raise SystemExit(f"--dpi must be a positive number, got {dpi}")
    if args.fresco_weight is not None and not (math.isfinite(args.fresco_weight) and args.fresco_weight >= 0):
        raise SystemExit(f"--fresco-weight must be a number >= 0, got {args.fresco_weight}")
    if args.json:   # a result that cannot be written is known before the run, not after it
        if Path(args.json).is_dir():
            raise SystemExit(f"--json {args.json}: is a directory; give a file name, e.g. "
                             f"{Path(args.json) / 'collection.json'}")
        try:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SystemExit(f"--json {args.json}: cannot make its folder ({exc.strerror or exc})")
    model = None
    if args.model:
        from common.matching.models import load_model
        from common.matching.proposals import ProposalStore
        from common.store import Store
        db = ProposalStore(args.db or Path(args.model) / "matches" / "proposals.sqlite")
        current = db.current_model()
        if current is None:
            raise SystemExit(f"--model {args.model}: the station has no match model yet")
        from common.matching.online import with_current_ribbon
        model = with_current_ribbon(load_model(Store(args.model), current["artifact"]))   # as the station's matcher
    out = args.out if args.out is not None else (Path(args.json).parent if args.json else Path("."))
    try:
        res = evaluate_collection(args.collection, dpi=dpi, model=model, out_dir=out,
                                  single_fresco=args.single_fresco, fresco_weight=args.fresco_weight,
                                  progress=progress)
    except ValueError as exc:
        hint = ""
        if "no true neighbour pair" in str(exc):
            hint = (" (no two placed pieces of one object come within 48 px of each other along 100 px of outline: "
                    "are truth.csv's x, y in the pictures' own pixels?)")
        raise SystemExit(f"--collection {args.collection}: {exc}{hint}")
    print(f"collection {res['collection']}: {res['n_fragments']} fragments, {res['n_true_pairs']} true neighbour "
          f"pairs, {res['dpi']:g} dpi, model {res['model']}" + (", ranked as one fresco" if res["single_fresco"] else "")
          + (f", same-fresco ratio weight {args.fresco_weight:g}" if args.fresco_weight is not None else ""))
    if res["skipped"]:
        print(f"left out {len(res['skipped'])} (the figures are of the rest):")
        for message in res["skipped"]:
            print(f"  - {message}")
    print("pooled top-k (links), mutual proximity: " + ", ".join(f"k={k}: {v:.3f}" for k, v in res["pooled_topk"].items())
          + "; by probability: " + ", ".join(f"k={k}: {v:.3f}" for k, v in res["pooled_topk_by_probability"].items()))
    print("within-object recall: " + ", ".join(f"@{k}: {v:.3f} (random {res['within_object_random'][k]:.3f}, "
                                                f"incidence {res['within_object_incidence'][k]:.3f}, "
                                                f"one query's order {res['within_object_recall_by_query'][k]:.3f})"
                                                for k, v in res["within_object_recall"].items()))
    print(f"the docking's geometric score puts a wrong pose (off by more than 5 deg or 5 mm) above the true one for "
          f"{res['wrong_pose_scores_above_truth']} of "
          f"{res['n_true_pairs']} true pairs")
    print(f"pair AP {res['pair_ap']:.3f} (by probability {res['pair_ap_by_probability']:.3f}); pose accuracy (5 deg, 5 mm) {res['pose_accuracy']:.3f} "
          f"(right among the proposed pose and its alternatives: {res['pose_offered']:.3f}; among all the docking's "
          f"candidates, the ceiling of any chooser: {res['pose_reachable']:.3f}); "
          f"{res['seconds']:.0f} s wall, {res['cpu_seconds']:.0f} s CPU")
    iv = res["intervals"]
    span = lambda lo_hi: f"{lo_hi[0]:.2f}-{lo_hi[1]:.2f}"  # noqa: E731
    print(f"{iv['level']:.0%} bootstrap intervals over the fragments (pairs for the poses) counted: pooled top-k "
          + ", ".join(f"k={k}: {span(v)}" for k, v in iv["pooled_topk"].items())
          + "; within-object " + ", ".join(f"@{k}: {span(v)}" for k, v in iv["within_object_recall"].items())
          + f"; pose accuracy {span(iv['pose_accuracy'])}, offered {span(iv['pose_offered'])}, "
            f"reachable {span(iv['pose_reachable'])}")
    if args.json:
        try:
            Path(args.json).write_text(to_json(res, indent=1))   # an undefined figure (NaN) as null
        except OSError as exc:
            raise SystemExit(f"--json {args.json}: cannot be written ({exc.strerror or exc}); the figures are "
                             "printed above")
        print(f"figures in {args.json}")
    if (Path(out) / "collection_examples.png").is_file():
        print(f"hits and misses drawn in {Path(out) / 'collection_examples.png'}")
    return 0


def _train(args, progress) -> int:
    from common.matching.models import save_model
    from common.matching.online import bootstrap_model
    from common.matching.proposals import ProposalStore
    from common.store import Store

    store = Store(args.train_model)
    model = bootstrap_model(n_fragments=args.fragments, seed=args.seed, dpi=args.dpi, progress=progress)
    ref = save_model(store, model, provenance={"command": "tessera evaluate --train-model"})
    db = ProposalStore(args.db or Path(args.train_model) / "matches" / "proposals.sqlite")
    db.add_model(model.version, ref.to_dict(), n_train=model.info.get("n_train"), note="tessera evaluate --train-model")
    print(f"model {model.version} installed: {ref.path} ({model.info.get('n_train')} training rows)")
    return 0
