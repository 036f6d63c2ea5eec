"""Per-arm evaluation success of an η-conditioned prototype run, and the arm a rule picks from the W epochs before
(most successes, then furthest stage), scored on the epoch it is picked for:  python select_arm.py RUN_DIR [W]"""
import sys, collections
from ccp_jax import outputs
d = sys.argv[1]; W = int(sys.argv[2]) if len(sys.argv) > 2 else 5
rows = outputs.read_rows(outputs.metrics_file(d))  # metrics.jsonl or its compacted metrics.jsonl.gz
by = collections.defaultdict(list)
for r in rows: by[r['member']].append(r)
arms = sorted(k for k in rows[0]['eval_end'] if k.startswith('arm_'))
print('epochs', len(by[0]), 'arms', arms)
sel_finals = []
for m, rs in sorted(by.items()):
    rs.sort(key=lambda r: r['epoch'])
    S = [[r['eval_end'][a] for a in arms] for r in rs]
    ST = [[r['eval_end']['armst_' + a[4:]] for a in arms] for r in rs]
    last = lambda col: sum(s[col] for s in S[-10:]) / 10
    finals = [last(i) for i in range(len(arms))]
    chosen = []
    for t in range(len(S)):
        lo = max(0, t - W)
        if t == 0: c = len(arms) // 2
        else:
            score = lambda i: (sum(S[u][i] for u in range(lo, t)), sum(ST[u][i] for u in range(lo, t)))
            c = max(range(len(arms)), key=score)
        chosen.append(S[t][c])
    sel = sum(chosen[-10:]) / 10
    sel_finals.append(sel)
    first = {a: next((r['env_steps'] for r in rs if r['eval_end'][a] > 0), None) for a in arms}
    print(f"member {m} seed {rs[0]['seed']}: per-arm final " + ' '.join(f'{a[4:]}:{f:.2f}' for a, f in zip(arms, finals)),
          f"| selected {sel:.2f} | first success per arm", {a[4:]: v for a, v in first.items()})
print('selected mean', sum(sel_finals) / len(sel_finals), 'solved(>0.5)', sum(s > 0.5 for s in sel_finals))
