/* Lock-step mode of the stage harness: the simulation owns time (stage_harness.c's top). */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <simavr/avr_uart.h>

#include "harness.h"

static int hexval(int c)
{
	return c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 :
	       c >= 'A' && c <= 'F' ? c - 'A' + 10 : -1;
}

int run_lockstep(void)
{
	avr_irq_t *uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	uint8_t *inq = NULL;
	size_t in_len = 0, in_pos = 0, in_cap = 0, line_cap = 0;
	char *line = NULL;
	int state = cpu_Running;
	while (!stop_requested && getline(&line, &line_cap, stdin) > 0) {
		if (!strncmp(line, "quit", 4))
			break;
		if (line[0] == 'w' && line[1] == ' ') {
			size_t n = strcspn(line + 2, "\r\n") / 2;
			if (in_pos == in_len)
				in_pos = in_len = 0;
			inq = grow(inq, &in_cap, in_len + n, 1);
			for (size_t i = 0; i < n; i++) {
				int hi = hexval(line[2 + 2 * i]), lo = hexval(line[3 + 2 * i]);
				if (hi >= 0 && lo >= 0)
					inq[in_len++] = (uint8_t)(hi << 4 | lo);
			}
			continue;
		}
		if (line[0] == 'h' && line[1] == ' ') {
			/* held in reset (the bootloader's time after DTR) up to this cycle: nothing
			 * runs meanwhile, then the firmware starts from its reset vector once */
			unsigned long long target = strtoull(line + 2, NULL, 10);
			if (target > avr->cycle)
				avr->cycle = target;
			avr_reset(avr);
			configure();
			in_pos = in_len = 0;
			uart_xon = 1;
			state = cpu_Running;
		} else if (!strncmp(line, "reset", 5)) {
			avr_reset(avr);
			configure();
			in_pos = in_len = 0;  /* the bootloader does not keep what came meanwhile */
			uart_xon = 1;
			state = cpu_Running;
		} else if (line[0] == 'r' && line[1] == ' ') {
			unsigned long long target = strtoull(line + 2, NULL, 10);
			while (avr->cycle < target && state != cpu_Done && state != cpu_Crashed) {
				state = avr_run(avr);
				while (in_pos < in_len && uart_xon)
					avr_raise_irq(uart_in, inq[in_pos++]);
			}
			if (n_out) {
				printf("u ");
				for (size_t i = 0; i < n_out; i++)
					printf("%02x", uart_out[i]);
				printf("\n");
				n_out = 0;
			}
			for (int i = 0; i < n_axes; i++) {
				axis_t *a = &axes[i];
				if (!a->n_edges)
					continue;
				printf("e %d", i);
				for (size_t k = 0; k < a->n_edges; k++)
					printf(" %lld", a->edges[k]);
				printf("\n");
				a->n_edges = 0;
			}
		} else {
			fprintf(stderr, "stage_harness: unknown command %s", line);
			continue;
		}
		printf("d %llu %d\n", (unsigned long long)avr->cycle, state);
		fflush(stdout);
	}
	free(line);
	free(inq);
	avr_terminate(avr);
	return 0;
}

