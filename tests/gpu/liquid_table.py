"""The diagnosis table of tests/gpu/liquid.sh (issue 81): for each model and each scene set
(`train`: the fluid scenes the runs trained on, `unseen`: seed 7), avg20 and whole-scene MSE
on the splash scenes and on all, over `constvel` and `persist`; the liquid's area (prediction
over truth) at steps 20, 200 and the end; the surge fronts within 10 % of the truth's step;
then the README's columns per family (avg20 and whole scenes, rope strain, liquid area).
Runs named LEVER-sN (tests/gpu/liquid.sh with SEEDS) are also summed up per lever, the
mean and the range over their seeds: at minutes of training the seeds' spread is as large as
a lever's effect (docs/splash.md).
Usage: liquid_table.py OUT NAME... (OUT holds eval's folders {train,unseen}-{h20,full})."""
import csv
import os
import re
import sys
from collections import defaultdict

REACH_SLACK = 1.0 / 64.0


def rows(path):
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def per_scene(path):
    """{predictor: {scene: avg}} from eval's table.csv (its first block: the average)."""
    out = defaultdict(dict)
    table = rows(path)
    if not table:
        return out
    avg = [c for c in table[0] if c != "scene"]
    avg = avg[: len(avg) // 2]
    for r in table:
        if r["scene"] == "Average":
            continue
        for c in avg:
            if r[c]:
                out[re.match(r"^(avg_full|avg\d+)_(.*)$", c).group(2)][r["scene"]] = float(r[c])
    return out


def mean(xs):
    xs = list(xs)
    return sum(xs) / len(xs) if xs else float("nan")


def ratio(scores, name, base, scenes):
    got = [scores[name][s] / scores[base][s] for s in scenes if s in scores[name] and scores[base].get(s)]
    return mean(got), mean(scores[name][s] for s in scenes if s in scores[name])


def areas(path, name):
    """Mean liquid area over truth at probes 20, 200 and the end (scenes within 10 %), and
    the liquid's kinetic energy over the truth's, averaged over every probe."""
    by = defaultdict(dict)
    energy = []
    for r in rows(path):
        if r["predictor"] == name and r["material"] == "liquid" and r["volume"]:
            by[r["scene"]][r["probe"]] = float(r["volume"])
            if r["energy"]:
                energy.append(float(r["energy"]))
    cells, end = [], []
    for probe in ("20", "200", "end"):
        end = [v[probe] for v in by.values() if probe in v]
        cells.append(f"{mean(end):.2f} ({sum(abs(x - 1) <= 0.1 for x in end)}/{len(end)})")
    return " / ".join(cells), f"{mean(energy):.2f}", mean(end)


def fronts(path, name):
    """Scenes whose front reaches the far wall within 10 % of the truth's step, of those the
    truth reaches it in, and how many it reaches at all."""
    series = defaultdict(lambda: defaultdict(dict))
    for r in rows(path):
        if r["front"]:
            series[r["scene"]][r["predictor"]][int(r["step"])] = float(r["front"])
    good = total = reached = 0
    for scene, by in series.items():
        truth = by.get("truth", {})
        if not truth or name not in by:
            continue
        wall = max(truth.values()) - REACH_SLACK
        reach = lambda s: next((k for k in sorted(s) if s[k] >= wall), None)
        t, p = reach(truth), reach(by[name])
        if t is None or t == 0:
            continue
        total += 1
        reached += p is not None
        good += p is not None and abs(p - t) <= 0.1 * t
    return f"{good}/{total} (reached {reached})"


def family_rows(out, tag, names):
    """The README's columns per model over a set: avg20 / `constvel` and whole scenes /
    `persist` per family (ratios of the family's means), the rope's strain at step 200
    and the liquid's area at the end per family (over the truth's)."""
    h20 = per_scene(f"{out}/{tag}-h20/table.csv")
    full = per_scene(f"{out}/{tag}-full/table.csv")
    plaus = rows(f"{out}/{tag}-full/plausibility.csv")
    families = ("multi", "fluid")

    def of_means(scores, name, base, family):
        scenes = [s for s in scores.get(name, {}) if s.startswith(family) and s in scores[base]]
        return mean(scores[name][s] for s in scenes) / mean(scores[base][s] for s in scenes)

    def measure(name, column, probe, material, family=""):
        return mean(float(r[column]) for r in plaus if r["predictor"] == name and r[column]
                    and r["probe"] == probe and r["material"] == material
                    and r["scene"].startswith(family))

    for name in names:
        if name not in h20 or name not in full:
            continue
        cells = [", ".join(f"{of_means(scores, name, base, f):.3f}" for f in families)
                 for scores, base in ((h20, "constvel"), (full, "persist"))]
        cells.append(f"{measure(name, 'strain', '200', 'rope'):.2f}")
        cells.append(", ".join(f"{measure(name, 'volume', 'end', 'liquid', f):.2f}"
                               for f in families))
        yield [tag, name, *cells]


def spread(values):
    """`mean [min, max]` of a lever's runs."""
    return f"{mean(values):.3g} [{min(values):.3g}, {max(values):.3g}]"


def main():
    out, names = sys.argv[1], [os.path.basename(n.rstrip("/")) for n in sys.argv[2:]]
    print("| set | model | avg20 splash (/constvel) | avg20 all (/constvel) "
          "| whole splash (/persist) | whole all (/persist) | liquid area 20 / 200 / end "
          "| energy | fronts |")
    print("| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |")
    # Per lever (a name's part before `-sN`): each set's splash avg20 and whole-scene ratios
    # and the liquid's area at the end, one value a seed.
    levers = defaultdict(lambda: defaultdict(list))
    for tag in ("train", "unseen"):
        h20 = per_scene(f"{out}/{tag}-h20/table.csv")
        full = per_scene(f"{out}/{tag}-full/table.csv")
        scenes = sorted(next(iter(h20.values()), {}))
        splash = [s for s in scenes if "splash" in s]
        for name in names:
            if name not in h20:
                print(f"| {tag} | {name} | (no rows) | | | | | | |")
                continue
            cells, ratios = [], []
            for scores, base in ((h20, "constvel"), (full, "persist")):
                for subset in (splash, scenes):
                    r, m = ratio(scores, name, base, subset)
                    cells.append(f"{m:.3e} ({r:.3f})")
                    ratios.append(r)
            plaus = f"{out}/{tag}-full/plausibility.csv"
            area, energy, end = areas(plaus, name)
            row = [tag, name, *cells, area, energy, fronts(f"{out}/{tag}-full/front.csv", name)]
            print("| " + " | ".join(row) + " |")
            lever = levers[(tag, re.sub(r"-s\d+$", "", name))]
            for key, v in (("avg20", ratios[0]), ("whole", ratios[3]), ("end", end)):
                lever[key].append(v)
    # The README's columns, per family.
    table = [row for tag in ("train", "unseen") for row in family_rows(out, tag, names)]
    if table:
        print("\n| set | model | avg20 / constvel (multi, fluid) | whole / persist (multi, fluid) "
              "| rope strain at 200 | liquid area at the end (multi, fluid) |")
        print("| --- | --- | --- | --- | ---: | --- |")
        for row in table:
            print("| " + " | ".join(row) + " |")
    if not any(len(v["avg20"]) > 1 for v in levers.values()):
        return
    print("\n| set | lever | seeds | avg20 splash / constvel | whole all / persist "
          "| liquid area at the end |")
    print("| --- | --- | ---: | --- | --- | --- |")
    for (tag, lever), v in levers.items():
        print(f"| {tag} | {lever} | {len(v['avg20'])} | {spread(v['avg20'])} "
              f"| {spread(v['whole'])} | {spread(v['end'])} |")


if __name__ == "__main__":
    main()
