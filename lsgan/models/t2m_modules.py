"""T2M's text-motion matching networks (Guo et al., CVPR 2022) and their contrastive loss.

The modules carry the parameter names of ``networks/modules.py`` of EricGuo5513/text-to-motion, so the state
dicts of its ``finest.tar`` load unchanged; our own evaluator reuses the motion side with configurable sizes:

- ``MovementConvEncoder(259, 512, 512)``: ``main`` = Conv1d(k4, s2, p1) -> Dropout(0.2) -> LeakyReLU(0.2),
  twice (the time axis shrinks 4x), then ``out_net`` Linear. The input drops the 4 foot-contact dims.
- ``MotionEncoderBiGRUCo(512, 1024, 512)``: ``input_emb`` Linear -> bidirectional GRU (learned initial
  state ``hidden`` (2,1,H)) over ``length // 4`` steps, both final states -> ``output_net``
  (Linear -> LayerNorm -> LeakyReLU(0.2) -> Linear).
- ``TextEncoderBiGRUCo(300, 15, 512, 512)``: GloVe word vector + ``pos_emb``(one-hot of 15 POS
  categories) -> ``input_emb`` -> bidirectional GRU -> ``output_net``.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence

from lsgan.data.skeleton import FEATURE_DIM
from lsgan.models.word_vectorizer import POS_ENUMERATOR, WORD_DIM

NUM_CONTACT_DIMS = 4  # foot contacts: the last 4 feature dims, not read by the evaluator


def init_weight(m: nn.Module) -> None:
    if isinstance(m, (nn.Conv1d, nn.Linear)):
        nn.init.xavier_normal_(m.weight)
        if m.bias is not None:
            nn.init.constant_(m.bias, 0)


class MovementConvEncoder(nn.Module):
    """(B, T, input) -> (B, T // 4, output): two strided convolutions, then a per-step Linear."""

    def __init__(self, input_size: int = FEATURE_DIM - NUM_CONTACT_DIMS, hidden_size: int = 512,
                 output_size: int = 512) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)
        self.main.apply(init_weight)
        self.out_net.apply(init_weight)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(inputs.permute(0, 2, 1)).permute(0, 2, 1))


class _BiGRUCo(nn.Module):
    """Bidirectional GRU over packed sequences from a learned initial state, both last states -> output_net."""

    def __init__(self, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size),
            nn.LayerNorm(hidden_size),
            nn.LeakyReLU(0.2),
            nn.Linear(hidden_size, output_size),
        )
        self.output_net.apply(init_weight)
        self.hidden_size = hidden_size
        self.hidden = nn.Parameter(torch.randn((2, 1, hidden_size)))

    def _run(self, input_embs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        hidden = self.hidden.repeat(1, input_embs.shape[0], 1)
        packed = pack_padded_sequence(input_embs, lengths.detach().cpu().long(), batch_first=True,
                                      enforce_sorted=False)
        _, last = self.gru(packed, hidden)  # (2, B, H), rows back in the input order
        return self.output_net(torch.cat([last[0], last[1]], dim=-1))


class MotionEncoderBiGRUCo(_BiGRUCo):
    """(B, T', input) movement codes and lengths in units (T // 4) -> (B, output)."""

    def __init__(self, input_size: int = 512, hidden_size: int = 1024, output_size: int = 512) -> None:
        super().__init__(hidden_size, output_size)
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.input_emb.apply(init_weight)

    def forward(self, inputs: torch.Tensor, m_lens: torch.Tensor) -> torch.Tensor:
        return self._run(self.input_emb(inputs), m_lens)


class TextEncoderBiGRUCo(_BiGRUCo):
    """(B, L, 300) word vectors, (B, L, 15) POS one-hots and lengths -> (B, output)."""

    def __init__(self, word_size: int = WORD_DIM, pos_size: int = len(POS_ENUMERATOR), hidden_size: int = 512,
                 output_size: int = 512) -> None:
        super().__init__(hidden_size, output_size)
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.input_emb = nn.Linear(word_size, hidden_size)
        self.input_emb.apply(init_weight)
        self.pos_emb.apply(init_weight)

    def forward(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, cap_lens: torch.Tensor) -> torch.Tensor:
        return self._run(self.input_emb(word_embs + self.pos_emb(pos_onehot)), cap_lens)


def contrastive_loss(a: torch.Tensor, b: torch.Tensor, negative: bool, margin: float) -> torch.Tensor:
    """T2M's ContrastiveLoss (Hadsell et al.): mean d^2 for matched pairs, mean max(0, margin - d)^2 otherwise.

    ``d`` is the Euclidean distance between rows (``F.pairwise_distance``, eps 1e-6 as there).
    """
    d = nn.functional.pairwise_distance(a, b, keepdim=True)
    if negative:
        return torch.clamp(margin - d, min=0.0).pow(2).mean()
    return d.pow(2).mean()
